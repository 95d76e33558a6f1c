"""Scan and L-frame sequence datasets over a SemanticKITTI layout (`root/sequences/XX/velodyne/NNNNNN.bin`) or a
nuScenes root (`root/v1.0-*/*.json` tables, `samples/LIDAR_TOP/*.pcd.bin`, `lidarseg/`).

Source: ../shared/reference/segmentation_protocols.md §5 (layouts; SemanticKITTI splits train 00-07, 09, 10 / val 08 /
test 11-21; relative pose of scan j in scan i = T_i^-1 T_j). Both families give the same items, `entries` as
(sequence, frame) pairs and their `label_set` (the nuScenes family is in `nuscenes_datasets`); `open_scans` /
`open_sequences` pick the family by format name. Items are plain numpy (training converts).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from u4d_aug.data.formats import label_path_for, load_kitti_frame, read_calib, read_kitti_label, read_poses
from u4d_aug.data.labels import SEMANTICKITTI_LABELS, map_semantickitti
from u4d_aug.data.nuscenes import NUSCENES_VERSION
from u4d_aug.data.nuscenes_datasets import NuscenesScanDataset, NuscenesSequenceDataset, resolve_scenes
from u4d_aug.errors import InputError

__all__ = [
    "DATASET_FORMATS",
    "SEMANTICKITTI_SPLITS",
    "NuscenesScanDataset",
    "NuscenesSequenceDataset",
    "ScanDataset",
    "SequenceDataset",
    "detect_format",
    "label_path_for",
    "list_frames",
    "list_sequences",
    "open_scans",
    "open_sequences",
    "resolve_scenes",
    "resolve_sequences",
    "scan_path",
]

PathLike = str | os.PathLike
DatasetFormat = Literal["semantickitti", "nuscenes"]
DATASET_FORMATS: tuple[str, ...] = ("semantickitti", "nuscenes")

SEMANTICKITTI_SPLITS: dict[str, tuple[str, ...]] = {
    "train": ("00", "01", "02", "03", "04", "05", "06", "07", "09", "10"),
    "val": ("08",),
    "test": tuple(f"{i:02d}" for i in range(11, 22)),
}


def _sequences_dir(root: PathLike) -> Path:
    if Path(root).is_file():
        raise InputError(f"{root}: is a file; expected a SemanticKITTI-layout folder (root/sequences/XX/velodyne/)")
    path = Path(root) / "sequences"
    if not path.is_dir():
        raise InputError(f"{path}: folder not found (expected a SemanticKITTI layout root/sequences/XX/velodyne/)")
    return path


def list_sequences(root: PathLike) -> list[str]:
    """Sorted names of the sequences under `root/sequences` that have a `velodyne/` folder."""
    sequences_dir = _sequences_dir(root)
    names = sorted(p.name for p in sequences_dir.iterdir() if (p / "velodyne").is_dir())
    if not names:
        raise InputError(f"{sequences_dir}: no sequence has a velodyne/ folder (expected sequences/XX/velodyne/*.bin)")
    return names


def list_frames(root: PathLike, seq: str) -> list[str]:
    """Sorted frame names (file stems, e.g. '000000') of `root/sequences/seq/velodyne/*.bin`."""
    velodyne = _sequences_dir(root) / seq / "velodyne"
    if not velodyne.is_dir():
        raise InputError(f"{velodyne}: velodyne/ folder not found (sequence {seq!r})")
    return sorted(p.name[: -len(".bin")] for p in velodyne.iterdir() if p.name.endswith(".bin") and p.is_file())


def scan_path(root: PathLike, seq: str, frame: str) -> Path:
    """`root/sequences/seq/velodyne/frame.bin`."""
    return Path(root) / "sequences" / seq / "velodyne" / f"{frame}.bin"


_RANGE = re.compile(r"^(\d+)-(\d+)$")


def expand_sequences(sequences: Sequence[str | int]) -> list[str]:
    """Sequence names of a list of names, ints (as '%02d') and 'A-B' ranges ('08-10' -> '08', '09', '10')."""
    names = []
    for s in sequences:
        match = _RANGE.match(s) if isinstance(s, str) else None
        if match:
            first, last = match.groups()
            if int(last) < int(first):
                raise InputError(f"sequences: range {s!r} ends before it starts")
            names += [f"{i:0{len(first)}d}" for i in range(int(first), int(last) + 1)]
        else:
            names.append(f"{s:02d}" if isinstance(s, int) else str(s))
    return names


def resolve_sequences(root: PathLike, sequences: str | Sequence[str | int] | None) -> list[str]:
    """None -> every sequence present; 'train'/'val'/'test' -> that split; 'A-B' -> A..B; a list -> those.

    List items are names, ints (as '%02d') or 'A-B' ranges ('00-87' -> '00', '01', ..., '87', zero-padded to the
    width of A). Every named sequence must exist with a `velodyne/` folder (InputError naming the missing path).
    """
    if sequences is None:
        return list_sequences(root)
    if isinstance(sequences, str):
        if sequences in SEMANTICKITTI_SPLITS:
            sequences = SEMANTICKITTI_SPLITS[sequences]
        elif _RANGE.match(sequences):
            sequences = [sequences]
        else:
            raise InputError(
                f"sequences={sequences!r}: expected a split name {sorted(SEMANTICKITTI_SPLITS)}, a range like "
                "'00-87' or a list of sequences"
            )
    names = expand_sequences(sequences)
    if not names:
        raise InputError(f"{root}: empty sequence list")
    for name in names:
        list_frames(root, name)  # raises when root/sequences/name/velodyne is missing
    return names


class ScanDataset:
    """Single scans of a SemanticKITTI-layout root; labels mapped to train ids 0..18 (19 = ignore).

    item = dict(points (N, 4) float32, labels (N,) int64 train ids or None, seq str, frame str)
    """

    label_set = SEMANTICKITTI_LABELS

    def __init__(
        self, root: PathLike, sequences: str | Sequence[str | int] | None = None, labeled_only: bool = False
    ) -> None:
        self.root = Path(root)
        self.sequences = resolve_sequences(self.root, sequences)
        self.entries: list[tuple[str, str]] = [
            (seq, frame)
            for seq in self.sequences
            for frame in list_frames(self.root, seq)
            if not labeled_only or label_path_for(scan_path(self.root, seq, frame)).is_file()
        ]

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, index: int) -> dict:
        seq, frame = self.entries[index]
        points, labels = _load_scan(self.root, seq, frame)
        return {"points": points, "labels": labels, "seq": seq, "frame": frame}

    def load_points(self, seq: str, frame: str) -> np.ndarray:
        """(N, 4) float32 points of one scan, NaN/inf rows dropped (the rows of its probability file)."""
        return load_kitti_frame(scan_path(self.root, seq, frame)).points

    def train_ids(self, index: int) -> np.ndarray | None:
        """(N_raw,) int64 train ids of entry `index` from its label file alone (None without one)."""
        path = label_path_for(scan_path(self.root, *self.entries[index]))
        return map_semantickitti(read_kitti_label(path)[0]) if path.is_file() else None


class SequenceDataset:
    """Windows of `num_frames` frames `stride` apart within one sequence, posed relative to the first frame.

    item = dict(points [L arrays (N_i, 4) float32], labels [L arrays (N_i,) int64 or None],
                poses (L, 4, 4) float64 T_0^-1 T_i (LiDAR; None if with_poses=False), seq, frames [L str])
    With `with_poses=True` (default) every sequence needs `poses.txt` and `calib.txt` (InputError otherwise),
    and frame names are read as line numbers of poses.txt.
    """

    def __init__(
        self,
        root: PathLike,
        num_frames: int,
        sequences: str | Sequence[str | int] | None = None,
        stride: int = 1,
        with_poses: bool = True,
    ) -> None:
        if num_frames < 1 or stride < 1:
            raise InputError(f"num_frames and stride must be >= 1, got num_frames={num_frames}, stride={stride}")
        self.root = Path(root)
        self.num_frames = num_frames
        self.stride = stride
        self.sequences = resolve_sequences(self.root, sequences)
        self.frames = {seq: list_frames(self.root, seq) for seq in self.sequences}
        self.poses = (
            {seq: _sequence_poses(self.root, seq, self.frames[seq]) for seq in self.sequences} if with_poses else None
        )
        span = (num_frames - 1) * stride + 1
        self.windows: list[tuple[str, int]] = [
            (seq, start) for seq in self.sequences for start in range(len(self.frames[seq]) - span + 1)
        ]
        if not self.windows:
            raise InputError(
                f"{self.root}: no sequence has the {span} frames that a window of {num_frames} x stride {stride} needs"
            )

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, index: int) -> dict:
        seq, start = self.windows[index]
        positions = range(start, start + self.num_frames * self.stride, self.stride)
        frames = [self.frames[seq][i] for i in positions]
        loaded = [_load_scan(self.root, seq, frame) for frame in frames]
        poses = None
        if self.poses is not None:
            absolute = self.poses[seq][list(positions)]  # (L, 4, 4) T_i in the frame of scan 0 of the sequence
            poses = np.linalg.inv(absolute[0]) @ absolute  # (L, 4, 4) T_0^-1 T_i
        return {
            "points": [points for points, _ in loaded],
            "labels": [labels for _, labels in loaded],
            "poses": poses,
            "seq": seq,
            "frames": frames,
        }


def _load_scan(root: Path, seq: str, frame: str) -> tuple[np.ndarray, np.ndarray | None]:
    path = scan_path(root, seq, frame)
    label_path = label_path_for(path)
    loaded = load_kitti_frame(path, label_path if label_path.is_file() else None)
    labels = map_semantickitti(loaded.semantic) if loaded.semantic is not None else None
    return loaded.points, labels


def _sequence_poses(root: Path, seq: str, frames: list[str]) -> np.ndarray:
    """LiDAR poses of `frames` (in order) from the sequence's poses.txt + calib.txt -> (F, 4, 4)."""
    folder = root / "sequences" / seq
    for name in ("poses.txt", "calib.txt"):
        if not (folder / name).is_file():
            raise InputError(f"{folder / name}: not found (SequenceDataset needs poses; pass with_poses=False to skip)")
    poses = read_poses(folder / "poses.txt", calib=read_calib(folder / "calib.txt"))
    try:
        index = np.array([int(frame) for frame in frames], dtype=np.int64)
    except ValueError:
        raise InputError(f"{folder / 'velodyne'}: frame names must be integers to index poses.txt") from None
    if len(index) and index.max() >= len(poses):
        raise InputError(
            f"{folder / 'poses.txt'}: {len(poses)} poses but frame {frames[int(index.argmax())]} needs more"
        )
    return poses[index]


# ------------------------------------------------------------------------------------------------------------
# by format name


def detect_format(root: PathLike) -> str:
    """The layout of a dataset root: 'nuscenes' with a v1.0-* table folder or samples/LIDAR_TOP/, 'semantickitti' with
    sequences/; InputError naming what was looked for when it has neither (or both)."""
    root = Path(root)
    if not root.is_dir():
        found = "is a file" if root.exists() else "folder not found"
        raise InputError(f"{root}: {found}; expected a dataset root (SemanticKITTI sequences/ or nuScenes v1.0-*/)")
    nuscenes = any(p.is_dir() for p in root.glob("v1.0-*")) or (root / "samples" / "LIDAR_TOP").is_dir()
    semantickitti = (root / "sequences").is_dir()
    if nuscenes and not semantickitti:
        return "nuscenes"
    elif semantickitti and not nuscenes:
        return "semantickitti"
    looked = "sequences/ (SemanticKITTI) and a v1.0-* table folder or samples/LIDAR_TOP/ (nuScenes)"
    found = "holds both" if nuscenes else "no dataset layout: looked for"
    raise InputError(f"{root}: {found} {looked}; name the layout with --format semantickitti|nuscenes")


def open_scans(
    root: PathLike,
    sequences: str | Sequence[str | int] | None = None,
    labeled_only: bool = False,
    data_format: str = "semantickitti",
    version: str = NUSCENES_VERSION,
) -> ScanDataset | NuscenesScanDataset:
    """The scan dataset of a root in `data_format` 'semantickitti' or 'nuscenes' (tables under ROOT/version)."""
    if data_format == "semantickitti":
        return ScanDataset(root, sequences, labeled_only)
    elif data_format == "nuscenes":
        return NuscenesScanDataset(root, sequences, labeled_only, version)
    raise InputError(f"data format {data_format!r}: expected one of {', '.join(DATASET_FORMATS)}")


def open_sequences(
    root: PathLike,
    num_frames: int,
    sequences: str | Sequence[str | int] | None = None,
    stride: int = 1,
    with_poses: bool = True,
    data_format: str = "semantickitti",
    version: str = NUSCENES_VERSION,
) -> SequenceDataset | NuscenesSequenceDataset:
    """The L-frame window dataset of a root in `data_format` 'semantickitti' or 'nuscenes'."""
    if data_format == "semantickitti":
        return SequenceDataset(root, num_frames, sequences, stride, with_poses)
    elif data_format == "nuscenes":
        return NuscenesSequenceDataset(root, num_frames, sequences, stride, with_poses, version)
    raise InputError(f"data format {data_format!r}: expected one of {', '.join(DATASET_FORMATS)}")
