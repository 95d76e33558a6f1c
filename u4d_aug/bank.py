"""A bank of generated scans in SemanticKITTI layout, written atomically and resumably.

BANK/sequences/00/velodyne/NNNNNN.bin   (N, 4) float32 points (read back with `read_kitti_scan`)
BANK/sequences/00/mask/NNNNNN.npy       (H, W) bool: the stage-1 mask m_u (predicted, or real in completion mode)
BANK/sequences/00/uncertainty/NNNNNN.npy (H, W) float16 entropy image, where the source had probabilities
BANK/sequences/00/stage1/NNNNNN.npy     (2, H, W) float16 x0_u in [-1, 1]: stage 1's output (u4d) or the real P_u
                                        that stage 2 completed (complete mode)
BANK/sequences/00/empty/NNNNNN         marker of a sample with no return at all (it gets no .bin: SemanticKITTI
                                        readers reject empty scans, and consumers should not see one)
BANK/sequences/00/labels/NNNNNN.label  all-ignore labels (0 = "unlabeled"), one per point (`u4d_aug.export_bank`)
BANK/sequences/00/{calib,poses,times}.txt  identity Tr and poses, times 0.1 s apart, one line per frame number
                                        (`write_sequence_files`; a sequence with its own poses keeps them)
BANK/manifest.json                      config, per-sample seeds and file sha256[:16], checkpoint sha256[:16], empty
                                        samples, completion
BANK/config.yaml, BANK/log.jsonl        the resolved config of the last run, one record per finished block
The .npy side files are written before the .bin (or marker), so its presence means the sample is complete; the
digests of a finished sample's files let a resumed run find a sample changed or truncated since (`changed_files`).

Sequence banks (generators trained on L > 1 frames) hold one sequence per sample: sample i is
BANK/sequences/NN/ (NN = i as %02d) with the same side folders and frames 000000 .. L-1 in velodyne/, so any
SemanticKITTI reader sees L consecutive scans. Completion-mode sequences also get poses.txt (the real frames'
poses relative to the first) and calib.txt with an identity Tr, which TTCE/CTC (`u4d evaluate`) read; so do
sequences of nets with an ego-motion input (the motion they were conditioned on). Poses are written before the
frames, and a sample is complete when all L frames are.

Once a run's samples are written, every sequence folder without poses of its own (single-frame banks, generated
sequences without an ego motion) gets identity placeholders so that SemanticKITTI readers find the files they
expect; the manifest's "placeholder_poses" says so (they are no ground truth for temporal metrics). Labels, times.txt
and the placeholders are written after the samples' digests are recorded (`record_digests`), outside them, so a
resumed run still finds its finished samples intact.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from u4d_aug.data.formats import (
    label_path_for,
    read_calib,
    read_poses,
    read_times,
    write_calib,
    write_kitti_scan,
    write_poses,
    write_times,
)
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_save_npy, atomic_write_bytes, atomic_write_json, file_sha256

logger = logging.getLogger(__name__)

BANK_SEQUENCE = "00"
MANIFEST = "manifest.json"
DIGESTS = "digests"
FRAME_SECONDS = 0.1  # KITTI's 10 Hz scan period: frame f of a bank sequence is at f * 0.1 s in its times.txt
CALIB_KEYS = ("P0", "P1", "P2", "P3", "Tr")  # the matrices of a KITTI odometry calib.txt


def sequence_name(index: int) -> str:
    """Sequence folder of sample `index` of a sequence bank ('00', '01', ..., '99', '100', ...)."""
    return f"{index:02d}"


@dataclass(frozen=True)
class BankLayout:
    """Paths of frame f of sample i of a bank rooted at `root`: scan i of sequence 00 when frames = 1, frame f
    of sequence `sequence_name(i)` when frames = L > 1."""

    root: Path
    frames: int = 1

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"BankLayout: frames must be >= 1, got {self.frames}")

    def sequence_dir(self, index: int = 0) -> Path:
        name = BANK_SEQUENCE if self.frames == 1 else sequence_name(index)
        return Path(self.root) / "sequences" / name

    @property
    def manifest_path(self) -> Path:
        return Path(self.root) / MANIFEST

    def _file(self, folder: str, index: int, frame: int, suffix: str) -> Path:
        if not 0 <= frame < self.frames:
            raise ValueError(f"BankLayout: frame {frame} outside 0..{self.frames - 1}")
        number = index if self.frames == 1 else frame
        return self.sequence_dir(index) / folder / f"{number:06d}{suffix}"

    def scan_path(self, index: int, frame: int = 0) -> Path:
        return self._file("velodyne", index, frame, ".bin")

    def mask_path(self, index: int, frame: int = 0) -> Path:
        return self._file("mask", index, frame, ".npy")

    def uncertainty_path(self, index: int, frame: int = 0) -> Path:
        return self._file("uncertainty", index, frame, ".npy")

    def empty_path(self, index: int, frame: int = 0) -> Path:
        return self._file("empty", index, frame, "")

    def stage1_path(self, index: int, frame: int = 0) -> Path:
        return self._file("stage1", index, frame, ".npy")

    def digest_path(self, index: int) -> Path:
        """BANK/digests/NNNNNN.json: the sample's file digests, written right after its last file (`record_digests`)."""
        return Path(self.root) / DIGESTS / f"{index:06d}.json"

    def poses_path(self, index: int) -> Path:
        return self.sequence_dir(index) / "poses.txt"

    def calib_path(self, index: int) -> Path:
        return self.sequence_dir(index) / "calib.txt"

    def is_empty(self, index: int, frame: int = 0) -> bool:
        return self.empty_path(index, frame).is_file()

    def is_done(self, index: int) -> bool:
        """Each frame's .bin (or empty marker) is written last: all present means every file of the sample is."""
        return all(self.scan_path(index, f).is_file() or self.is_empty(index, f) for f in range(self.frames))


def sample_files(layout: BankLayout, index: int) -> list[Path]:
    """The files of sample `index` that exist: per frame the side .npy files and the .bin (or empty marker), and
    a sequence bank's poses.txt and calib.txt."""
    paths = []
    for frame in range(layout.frames):
        paths += [
            layout.mask_path(index, frame),
            layout.uncertainty_path(index, frame),
            layout.stage1_path(index, frame),
            layout.scan_path(index, frame),
            layout.empty_path(index, frame),
        ]
    if layout.frames > 1:
        paths += [layout.poses_path(index), layout.calib_path(index)]
    return [path for path in paths if path.is_file()]


def sample_digests(layout: BankLayout, index: int) -> dict[str, str]:
    """{path relative to the bank: sha256[:16]} of every file of sample `index` (the manifest's record)."""
    return {path.relative_to(layout.root).as_posix(): file_sha256(path) for path in sample_files(layout, index)}


def changed_files(layout: BankLayout, recorded: dict[str, str]) -> list[str]:
    """Recorded files of a sample that are missing or whose bytes no longer match their digest."""
    changed = []
    for name, digest in recorded.items():
        path = Path(layout.root) / name
        if not path.is_file() or file_sha256(path) != digest:
            changed.append(name)
    return changed


def remove_sample(layout: BankLayout, index: int) -> None:
    """Delete every file of sample `index` (and an exported label file, which would no longer fit the scan), so
    that a resumed `u4d generate` writes it again."""
    for path in sample_files(layout, index):
        path.unlink(missing_ok=True)
    for frame in range(layout.frames):
        label_path_for(layout.scan_path(index, frame)).unlink(missing_ok=True)


def record_digests(layout: BankLayout, index: int) -> dict[str, str]:
    """Write the digests of sample `index`'s files to `layout.digest_path(index)` (atomically, right after its last
    file): a sample on disk without its digests was cut short and is generated again on resume."""
    digests = sample_digests(layout, index)
    atomic_write_json(layout.digest_path(index), digests)
    return digests


def recorded_digests(layout: BankLayout, entry: dict[str, Any]) -> dict[str, str] | None:
    """The digests the manifest entry records, else those of the sample's digest file, else None."""
    recorded = entry.get("sha256")
    if isinstance(recorded, dict):
        return recorded
    path = layout.digest_path(entry["index"])
    try:
        recorded = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return recorded if isinstance(recorded, dict) else None


def verify_samples(layout: BankLayout, manifest: dict[str, Any] | None) -> dict[int, dict[str, str]]:
    """{index: digests} of the finished samples whose files match their recorded digests; a changed sample, or one
    whose digests were never recorded (its run was killed while writing it), is removed (warning)."""
    verified = {}
    for entry in (manifest or {}).get("samples", []):
        index = entry.get("index")
        if not isinstance(index, int) or not layout.is_done(index):
            continue
        recorded = recorded_digests(layout, entry)
        if recorded is None:
            logger.warning("%s: sample %d has no recorded digests (cut short); generating it again", layout.root, index)
            remove_sample(layout, index)
            continue
        changed = changed_files(layout, recorded)
        if changed:
            logger.warning(
                "%s: sample %d changed since it was written (%s); generating it again", layout.root, index, changed[0]
            )
            remove_sample(layout, index)
        else:
            verified[index] = recorded
    return verified


def write_sample(
    layout: BankLayout,
    index: int,
    points: np.ndarray,
    mask: np.ndarray | None = None,
    uncertainty: np.ndarray | None = None,
    x0_u: np.ndarray | None = None,
    frame: int = 0,
) -> None:
    """Write frame `frame` of sample `index`: side files first, the scan last (an empty scan as a marker)."""
    if mask is not None:
        atomic_save_npy(layout.mask_path(index, frame), np.asarray(mask, dtype=bool))
    if uncertainty is not None:
        atomic_save_npy(layout.uncertainty_path(index, frame), np.asarray(uncertainty, dtype=np.float16))
    if x0_u is not None:
        atomic_save_npy(layout.stage1_path(index, frame), np.asarray(x0_u, dtype=np.float16))
    if len(points) == 0:
        atomic_write_bytes(layout.empty_path(index, frame), b"0 points\n")
    else:
        write_kitti_scan(layout.scan_path(index, frame), np.asarray(points, dtype=np.float32))


def write_sequence_poses(layout: BankLayout, index: int, poses: np.ndarray) -> None:
    """calib.txt (identity Tr and P0-P3 = [I | 0]) and poses.txt of the (L, 4, 4) LiDAR poses of sample `index`."""
    poses = np.asarray(poses, dtype=np.float64)
    if layout.frames == 1 or poses.shape != (layout.frames, 4, 4):
        raise ValueError(f"write_sequence_poses: expected ({layout.frames}, 4, 4) poses of a sequence bank")
    write_calib(layout.calib_path(index), identity_calib())
    write_poses(layout.poses_path(index), poses)  # with Tr = I the LiDAR poses are the cam0 poses


def identity_calib() -> dict[str, np.ndarray]:
    """calib.txt of a bank sequence: P0-P3 = [I | 0] and Tr = I (the LiDAR frame is the camera frame)."""
    return {key: np.eye(4)[:3] for key in CALIB_KEYS}


def has_own_poses(manifest: dict[str, Any]) -> bool:
    """Whether a bank's sequences carry poses of their own: completion-mode and ego-motion sequence banks."""
    return manifest.get("frames", 1) > 1 and (manifest.get("mode") == "complete" or "motion" in manifest)


def _holds(path: Path, reader: Callable[[Path], Any], expected: Any) -> bool:
    """Whether `path` reads back (with `reader`) as `expected`, so that writing it again would change nothing."""
    if not path.is_file():
        return False
    try:
        found = reader(path)
    except InputError:
        return False
    if isinstance(expected, dict):
        return found.keys() == expected.keys() and all(np.array_equal(found[k], expected[k]) for k in expected)
    return bool(np.array_equal(found, expected))


def write_sequence_files(folder: Path, frames: int, own_poses: bool) -> None:
    """calib.txt, poses.txt and times.txt of a bank sequence of frame numbers 0..frames-1 (KITTI odometry layout,
    one line per frame number): times f * 0.1 s; with own_poses the sequence's calib and poses are kept, else they
    are identity placeholders. Files that already hold this are not written again."""
    times = np.round(np.arange(frames) * FRAME_SECONDS, 6)  # 0.1, 0.2, 0.3 exactly as text
    if not _holds(folder / "times.txt", read_times, times):
        write_times(folder / "times.txt", times)
    if own_poses:
        return
    if not _holds(folder / "calib.txt", read_calib, identity_calib()):
        write_calib(folder / "calib.txt", identity_calib())
    if not _holds(folder / "poses.txt", read_poses, np.tile(np.eye(4), (frames, 1, 1))):
        write_poses(folder / "poses.txt", np.tile(np.eye(4), (frames, 1, 1)))  # (frames, 4, 4)


def write_bank_sequence_files(layout: BankLayout, count: int, own_poses: bool) -> None:
    """`write_sequence_files` of every sequence of a bank's first `count` samples: the one sequence of a
    single-frame bank (a line per sample index, empty samples too) and each finished sample's sequence of a sequence
    bank (a sample removed to be generated again takes its files with it: `remove_sample`)."""
    if layout.frames == 1:
        if count > 0 and layout.sequence_dir().is_dir():
            write_sequence_files(layout.sequence_dir(), count, own_poses)
        return
    for index in range(count):
        if layout.is_done(index):
            write_sequence_files(layout.sequence_dir(index), layout.frames, own_poses)


def read_manifest(root: str | Path) -> dict[str, Any] | None:
    """The bank's manifest, or None if it has none yet."""
    path = BankLayout(Path(root)).manifest_path
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid json ({getattr(exc, 'msg', exc)})") from None
    check_manifest_shape(record, path)
    return record


# the fields a bank's readers use, with the type each must have when present (isinstance, written out)
_FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "samples": (list,),
    "frames": (int,),
    "height": (int,),
    "width": (int,),
    "sensor": (str,),
    "row_mode": (str,),
    "mode": (str,),
    "complete": (bool,),
    "empty": (list,),
    "export": (dict,),
    "config": (dict,),
}


_TYPE_WORDS = {list: "a list", int: "an integer", str: "a string", bool: "true or false", dict: "an object"}


def check_manifest_shape(record: Any, path: Path) -> None:
    """InputError naming the field when a manifest is valid json of the wrong shape: not an object, a field of the
    wrong type, a sample entry without an integer index, a size below 1."""
    if not isinstance(record, dict):
        raise InputError(f"{path}: expected a json object (a bank's manifest), got a {type(record).__name__}")
    for key, types in _FIELD_TYPES.items():
        value = record.get(key)
        if value is None:
            continue
        if not isinstance(value, types) or (types == (int,) and isinstance(value, bool)):
            expected = _TYPE_WORDS[types[0]]
            raise InputError(f"{path}: '{key}' must be {expected}, got {type(value).__name__} {value!r:.40}")
        if key in ("frames", "height", "width") and isinstance(value, int) and value < 1:
            raise InputError(f"{path}: '{key}' must be >= 1, got {value}")
    for position, entry in enumerate(record.get("samples") or []):
        index = entry.get("index") if isinstance(entry, dict) else None
        if not isinstance(index, int) or isinstance(index, bool) or index < 0:
            raise InputError(f"{path}: samples[{position}] must be an object with an integer 'index' >= 0")


def check_compatible(root: str | Path, identity: dict[str, Any]) -> None:
    """Refuse to add samples to a bank written with another config or other checkpoints."""
    old = read_manifest(root)
    if old is None:
        return
    for key, value in identity.items():
        if old.get(key) != value:
            raise InputError(
                f"{BankLayout(Path(root)).manifest_path}: bank was generated with a different {key}; "
                "choose another --out or delete the bank"
            )


def named_banks(texts: list[str], flag: str = "--bank") -> dict[str, Path]:
    """'NAME=DIR' arguments -> {NAME: DIR}, each DIR a folder with sequences/ (a bank, or real data in its layout)."""
    banks: dict[str, Path] = {}
    for text in texts:
        name, sep, folder = text.partition("=")
        name = name.strip()
        if not sep or not name or not folder.strip():
            raise InputError(f"{flag} {text!r}: expected NAME=DIR (a folder with sequences/), e.g. u4d=runs/bank")
        root = Path(folder)
        if not (root / "sequences").is_dir():
            raise InputError(f"{flag} {text!r}: {root / 'sequences'} is not a folder (expected a u4d generate bank)")
        if name in banks:
            raise InputError(f"{flag} {text!r}: the name {name!r} is given twice")
        banks[name] = root
    return banks


def sequence_ids(root: str | Path) -> list[str]:
    """Names of the folders in ROOT/sequences, sorted; an InputError when there are none."""
    folder = Path(root) / "sequences"
    ids = sorted(p.name for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []
    if not ids:
        raise InputError(f"{folder}: no sequence folders")
    return ids


def write_manifest(root: str | Path, manifest: dict[str, Any]) -> None:
    """Write BANK/manifest.json atomically."""
    atomic_write_json(BankLayout(Path(root)).manifest_path, manifest)
