"""`u4d export BANK --layout semantickitti|mmdet3d|pointcept [--out DIR]`: a bank as each codebase's dataset reads it.

Labels: sequences/NN/labels/NNNNNN.label beside every velodyne/NNNNNN.bin, one uint32 per point of the .bin
(SemanticKITTI encoding: lower 16 bits semantic id, upper 16 instance id), all 0 = "unlabeled", which
SemanticKITTI-format loaders map to their ignore index (mmdetection3d `labels_map` 0 -> 19 = ignore_index,
Pointcept `learning_map` 0 -> ignore_index -1, LaserMix 0 = ignore). Without them Pointcept reads every point of
a scan as class 0 (`SemanticKITTIDataset.get_data`: no label file -> np.zeros).

Layouts (data_root = OUT; without --out the bank itself, in place, for semantickitti and mmdet3d):
  semantickitti  sequences/NN/{velodyne,labels}/ and calib.txt, poses.txt, times.txt (`bank.write_sequence_files`)
  mmdet3d        the semantickitti tree and `semantickitti_infos_train.pkl` as mmdetection3d v1.4.0's
                 `tools/dataset_converters/semantickitti_converter.py::get_semantickitti_info` writes it:
                     {"metainfo": {"DATASET": "SemanticKITTI"},
                      "data_list": [{"lidar_points": {"lidar_path": "sequences/00/velodyne/000000.bin",
                                                      "num_pts_feats": 4},
                                     "pts_semantic_mask_path": "sequences/00/labels/000000.label",
                                     "sample_id": "00"}, ...]}
                 (sample_id = str(int(sequence)) + str(int(frame)), as the converter joins its ints), paths
                 relative to data_root, which `SemanticKittiDataset`'s default data_prefix ('' for pts and
                 pts_semantic_mask) joins them to (`Seg3DDataset.parse_data_info`)
  pointcept      dataset/sequences/SS/{velodyne,labels}/ as Pointcept's `SemanticKITTIDataset.get_data_list` lists
                 them: every sequence of its train split (00-07, 09, 10) with a velodyne/ folder (it lists each one),
                 nothing but scans in them; the j-th bank sequence goes to train sequence j mod 10, its frames
                 numbered after those already there (OUT/u4d_export.json states the mapping)

In place, label and sequence files are outside the per-sample digests of the manifest (`bank.sample_files`), so a
resumed `u4d generate` still finds every finished sample intact, and the manifest's "export" entry records what
was written. Into another --out, scans and the bank's labels are hard links into the bank where the file system
allows (copies otherwise; every write is atomic, so a later write replaces a link and never changes the bank's
file), nothing is written outside --out, and OUT/u4d_export.json records the export.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import logging
import os
import pickle
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from u4d_aug.bank import (
    FRAME_SECONDS,
    BankLayout,
    has_own_poses,
    read_manifest,
    write_bank_sequence_files,
    write_manifest,
    write_sequence_files,
)
from u4d_aug.data.formats import label_path_for, write_kitti_label
from u4d_aug.errors import InputError
from u4d_aug.io import (
    TEMP_PREFIX,
    TEMP_SUFFIX,
    atomic_copy,
    atomic_write_bytes,
    dumps_json,
    make_folder,
    remove_temp_files,
)
from u4d_aug.outfolder import folder_content
from u4d_aug.runlock import LOCK_NAME, holder_text, is_stale, read_holder, run_lock

logger = logging.getLogger(__name__)

Layout = Literal["semantickitti", "mmdet3d", "pointcept"]
LAYOUTS: tuple[Layout, ...] = ("semantickitti", "mmdet3d", "pointcept")
INFOS_NAME = "semantickitti_infos_train.pkl"
MMDET3D_VERSION = "1.4.0"  # the mmdetection3d release whose SemanticKITTI info layout `mmdet3d_infos` follows
# Pointcept `SemanticKITTIDataset.get_data_list`: split2seq["train"], read under data_root/dataset/sequences
POINTCEPT_TRAIN = ("00", "01", "02", "03", "04", "05", "06", "07", "09", "10")
EXPORT_RECORD = "u4d_export.json"  # OUT's record of a tree export (never in a bank: its manifest records those)
SEQUENCE_FILES = ("calib.txt", "poses.txt", "times.txt")
POINT_BYTES = 16  # (x, y, z, intensity) float32
PICKLE_PROTOCOL = 4  # readable by every python 3 that mmdetection3d supports
IGNORE_LABELS = {"kind": "ignore", "semantic": 0, "instance": 0}  # all 0 = "unlabeled": the ignore index of readers


@dataclass(frozen=True)
class Placement:
    """A bank scan and where it goes in the export tree (path relative to OUT)."""

    source: Path
    target: str


def bank_scans(root: Path) -> list[Path]:
    """Every velodyne/*.bin of the bank's sequences, in sequence then frame order."""
    return sorted((Path(root) / "sequences").glob("*/velodyne/*.bin"))


def scan_point_count(path: Path) -> int:
    """Number of (x, y, z, intensity) float32 records of a KITTI .bin (the count every loader reads, NaN rows too)."""
    size = path.stat().st_size
    if size % POINT_BYTES:
        raise InputError(f"{path}: {size} bytes is not a whole number of 16-byte points (truncated scan)")
    return size // POINT_BYTES


def has_labels(scan: Path, label: Path) -> bool:
    """Whether `label` holds one label per point of `scan`."""
    return label.is_file() and label.stat().st_size == 4 * scan_point_count(scan)


def write_ignore_labels(scan: Path) -> bool:
    """Write the all-0 ("unlabeled") .label of `scan` unless one with a label per point is there; True if written."""
    label = label_path_for(scan)
    if has_labels(scan, label):
        return False
    count = scan_point_count(scan)
    if label.is_file():
        labels = label.stat().st_size // 4
        logger.warning("%s: %d labels for %d points (scan written again since); rewriting", label, labels, count)
    write_kitti_label(label, np.zeros(count, dtype=np.uint16))
    return True


def sample_id(sequence: str, frame: str) -> str:
    """mmdetection3d's SemanticKITTI sample_id: str(sequence) + str(frame) of the two numbers, as its converter joins
    them ('0' + '12' -> '012'; the converter's ids are not unique either)."""
    return f"{int(sequence)}{int(frame)}"


def mmdet3d_infos(data_root: Path, scans: list[Path]) -> dict[str, Any]:
    """The info dict of mmdetection3d v1.4.0's SemanticKITTI converter for `scans` (paths relative to data_root)."""
    data_list = []
    for scan in scans:
        entry = {
            "lidar_points": {"lidar_path": scan.relative_to(data_root).as_posix(), "num_pts_feats": 4},
            "pts_semantic_mask_path": label_path_for(scan).relative_to(data_root).as_posix(),
            "sample_id": sample_id(scan.parent.parent.name, scan.stem),
        }
        data_list.append(entry)
    return {"metainfo": {"DATASET": "SemanticKITTI"}, "data_list": data_list}


def _number_order(name: str) -> tuple[int, str]:
    return len(name), name  # '9' < '10' < '100' for names of digits


def frame_number(scan: Path) -> int:
    """The frame number of a bank scan's file name (NNNNNN.bin)."""
    if not scan.stem.isdigit():
        raise InputError(f"{scan}: expected a numbered scan NNNNNN.bin in a bank")
    return int(scan.stem)


def pointcept_sequences(scans: list[Path]) -> list[dict[str, Any]]:
    """{bank, pointcept, frame_offset, scans} per bank sequence (in number order): the j-th goes to Pointcept train
    sequence j mod 10, bank frame f to frame f + frame_offset, after the frames of the bank sequences before it."""
    by_sequence: dict[str, list[Path]] = {}
    for scan in scans:
        by_sequence.setdefault(scan.parent.parent.name, []).append(scan)
    offsets = dict.fromkeys(POINTCEPT_TRAIN, 0)
    mapping = []
    for position, sequence in enumerate(sorted(by_sequence, key=_number_order)):
        target = POINTCEPT_TRAIN[position % len(POINTCEPT_TRAIN)]
        frames = [frame_number(scan) for scan in by_sequence[sequence]]
        mapping.append({"bank": sequence, "pointcept": target, "frame_offset": offsets[target], "scans": len(frames)})
        offsets[target] += max(frames) + 1
    return mapping


def tree_plan(root: Path, scans: list[Path], layout: Layout) -> tuple[list[Placement], list[dict[str, Any]]]:
    """Where each scan goes in the export tree of `layout`, and the bank -> Pointcept sequence mapping (pointcept)."""
    if layout != "pointcept":
        return [Placement(scan, scan.relative_to(root).as_posix()) for scan in scans], []
    mapping = pointcept_sequences(scans)
    where = {entry["bank"]: entry for entry in mapping}
    plan = []
    for scan in scans:
        entry = where[scan.parent.parent.name]
        frame = frame_number(scan) + entry["frame_offset"]
        plan.append(Placement(scan, f"dataset/sequences/{entry['pointcept']}/velodyne/{frame:06d}.bin"))
    return plan, mapping


def place_file(source: Path, target: Path) -> str:
    """Make `target` hold `source`'s bytes: a hard link (atomically renamed into place) where the file system allows,
    else an atomic copy (a target that already holds them is left as it is); how it holds them: 'linked' or
    'copied'."""
    if target.is_file() and os.path.samefile(source, target):
        return "linked"
    if target.is_file() and filecmp.cmp(source, target, shallow=False):
        return "copied"
    make_folder(target.parent)
    temp = target.parent / f"{TEMP_PREFIX}{target.name}.{secrets.token_hex(4)}{TEMP_SUFFIX}"
    try:
        os.link(source, temp)
    except OSError:  # another file system, or links refused (protected_hardlinks): copy
        atomic_copy(source, target)
        return "copied"
    try:
        os.replace(temp, target)
    except OSError as exc:
        temp.unlink(missing_ok=True)
        raise InputError(f"{target}: cannot write ({exc.strerror or exc})") from None
    return "linked"


def check_export_folder(out: Path, layout: Layout) -> None:
    """InputError unless OUT is missing, empty, or holds an earlier export of the same layout (u4d_export.json)."""
    content = folder_content(out)
    if not content:
        return
    record_path = out / EXPORT_RECORD
    if not record_path.is_file():
        shown = ", ".join(content[:4]) + (", ..." if len(content) > 4 else "")
        raise InputError(
            f"{out}: holds {shown} and no {EXPORT_RECORD}; choose an empty --out (an export writes only into a "
            "folder that is empty or holds an earlier export)"
        )
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        record = None
    if not isinstance(record, dict) or record.get("layout") != layout:
        found = record.get("layout") if isinstance(record, dict) else "an unreadable record"
        raise InputError(f"{record_path}: an export of layout {found}, not {layout}; choose another --out")


def check_bank_idle(root: Path) -> None:
    """InputError when a live run holds the bank's lock (`u4d generate` writing it): its scans are not all there."""
    holder = read_holder(root / LOCK_NAME)
    if holder and not is_stale(holder):
        raise InputError(f"{root}: being written by another run ({holder_text(holder)}); export it once that run ends")


def open_bank(root: Path) -> dict[str, Any]:
    """The bank's manifest; InputError when `root` is no bank."""
    if not root.is_dir():
        raise InputError(f"{root}: not a bank (no such folder)")
    manifest = read_manifest(root)
    if manifest is None:
        raise InputError(f"{root}: not a bank (no manifest.json; `u4d generate --out` writes one)")
    return manifest


def sequence_frames(manifest: dict[str, Any]) -> int:
    """Frame numbers per sequence of a bank: its frames L, or a single-frame bank's sample count (one sequence)."""
    frames = manifest.get("frames", 1)
    return frames if frames > 1 else len(manifest.get("samples", []))


def export_bank(root: str | Path, layout: Layout = "semantickitti", out: str | Path | None = None) -> dict[str, Any]:
    """Write the bank in `layout` (in place without `out`, pointcept excepted); returns the export's record."""
    if layout not in LAYOUTS:
        raise InputError(f"layout {layout!r}: expected one of {', '.join(LAYOUTS)}")
    root = Path(root)
    manifest = open_bank(root)
    target = root if out is None else Path(out)
    in_place = target.resolve() == root.resolve()
    if layout == "pointcept" and in_place:
        raise InputError(
            f"{root}: --layout pointcept writes a tree OUT/dataset/sequences; give --out DIR (not the bank)"
        )
    if in_place:
        with run_lock(root):  # not while `u4d generate` writes this bank
            return export_in_place(root, open_bank(root), layout)
    check_export_folder(target, layout)
    check_bank_idle(root)
    with run_lock(target):
        return export_tree(root, manifest, layout, target)


def export_in_place(root: Path, manifest: dict[str, Any], layout: Layout) -> dict[str, Any]:
    """Labels, sequence files and (mmdet3d) the info file in the bank itself; the manifest's "export" entry."""
    scans = bank_scans(root)
    written = sum(write_ignore_labels(scan) for scan in scans)
    logger.info("%s: %d label files written, %d already there", root, written, len(scans) - written)
    own_poses = has_own_poses(manifest)
    write_bank_sequence_files(BankLayout(root, manifest.get("frames", 1)), len(manifest.get("samples", [])), own_poses)
    record = dict(manifest.get("export") or {})
    record["labels"] = {**IGNORE_LABELS, "files": len(scans)}
    record["sequence_files"] = {"poses": "own" if own_poses else "identity", "seconds_per_frame": FRAME_SECONDS}
    if layout == "mmdet3d":
        write_if_changed(root / INFOS_NAME, pickle.dumps(mmdet3d_infos(root, scans), protocol=PICKLE_PROTOCOL))
        record["mmdet3d_infos"] = {"path": INFOS_NAME, "samples": len(scans), "mmdet3d_version": MMDET3D_VERSION}
    updated = {**manifest, "export": record, "placeholder_poses": not own_poses}
    if updated != manifest:
        write_manifest(root, updated)  # samples and their digests unchanged
    return record


def export_tree(root: Path, manifest: dict[str, Any], layout: Layout, out: Path) -> dict[str, Any]:
    """The export tree of `layout` in OUT (links into the bank, else copies), stale files of an earlier export of
    the bank removed, and OUT/u4d_export.json."""
    removed = remove_temp_files(out)
    if removed:
        logger.info("%s: removed %d temp file(s) of a killed export", out, removed)
    scans = bank_scans(root)
    plan, mapping = tree_plan(root, scans, layout)
    counts = {"linked": 0, "copied": 0, "written": 0}  # how OUT holds the files: links into the bank, copies, its own
    for placement in plan:
        target = out / placement.target
        counts[place_file(placement.source, target)] += 1
        source_label = label_path_for(placement.source)
        if has_labels(placement.source, source_label):
            counts[place_file(source_label, label_path_for(target))] += 1
        else:  # a bank without labels: OUT gets its own
            write_ignore_labels(target)
            counts["written"] += 1
    if layout == "pointcept":
        for sequence in POINTCEPT_TRAIN:  # Pointcept lists every train sequence's velodyne/ folder
            make_folder(out / "dataset" / "sequences" / sequence / "velodyne")
    else:
        _place_sequence_files(root, manifest, out, counts)
    _remove_stale(out, layout, {out / p.target for p in plan} | {label_path_for(out / p.target) for p in plan})
    record: dict[str, Any] = {
        "layout": layout,
        "bank": str(root.resolve()),
        "data_root": str(out.resolve()),
        "scans": len(plan),
        "labels": {**IGNORE_LABELS, "files": len(plan)},
        "files": counts,
    }
    if layout == "pointcept":
        record["pointcept"] = {"split": "train", "sequences": mapping}
    if layout == "mmdet3d":
        infos = mmdet3d_infos(out, [out / p.target for p in plan])
        write_if_changed(out / INFOS_NAME, pickle.dumps(infos, protocol=PICKLE_PROTOCOL))
        record["mmdet3d_infos"] = {"path": INFOS_NAME, "samples": len(plan), "mmdet3d_version": MMDET3D_VERSION}
    write_if_changed(out / EXPORT_RECORD, (dumps_json(record, indent=2) + "\n").encode())
    return record


def write_if_changed(path: Path, data: bytes) -> None:
    """Write `data` to `path` atomically unless it already holds them (a repeated export changes no file)."""
    if not (path.is_file() and path.read_bytes() == data):
        atomic_write_bytes(path, data)


def _place_sequence_files(root: Path, manifest: dict[str, Any], out: Path, counts: dict[str, int]) -> None:
    """calib.txt, poses.txt, times.txt of each exported sequence: the bank's where it has them, else written."""
    own_poses = has_own_poses(manifest)
    for folder in sorted({path.parent.parent for path in bank_scans(root)}):
        target = out / folder.relative_to(root)
        for name in SEQUENCE_FILES:
            if (folder / name).is_file():
                counts[place_file(folder / name, target / name)] += 1
        write_sequence_files(target, sequence_frames(manifest), own_poses)  # what the bank lacks (older banks)


def _remove_stale(out: Path, layout: Layout, keep: set[Path]) -> None:
    """Remove scans and labels of an earlier export that this one no longer holds (readers list whole folders)."""
    base = out / "dataset" / "sequences" if layout == "pointcept" else out / "sequences"
    for path in sorted(base.glob("*/velodyne/*")) + sorted(base.glob("*/labels/*")):
        if path not in keep and (path.is_file() or path.is_symlink()):
            logger.info("%s: not in this export of the bank; removed", path)
            path.unlink()


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d export BANK [--layout semantickitti|mmdet3d|pointcept] [--out DIR]`."""
    parser.add_argument("bank", type=Path, help="a bank written by `u4d generate` or `u4d bank-real`")
    parser.add_argument(
        "--layout",
        choices=LAYOUTS,
        default=None,
        help="semantickitti: labels (all 0 = unlabeled) and calib/poses/times beside the scans; mmdet3d: the same and "
        f"{INFOS_NAME} (mmdetection3d v1.x); pointcept: OUT/dataset/sequences of Pointcept's train split "
        "(default: mmdet3d, which holds the semantickitti layout)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="data_root of the export (links into the bank); default: the bank itself"
    )
    parser.add_argument("--labels", action="store_true", help="deprecated: --layout semantickitti")
    parser.add_argument("--mmdet3d-infos", action="store_true", help="deprecated: --layout mmdet3d")


def chosen_layout(args: argparse.Namespace) -> Layout:
    """--layout, else the layout the deprecated flags name (--mmdet3d-infos, or neither: mmdet3d; --labels alone:
    semantickitti)."""
    if args.layout is not None:
        return args.layout
    if args.labels and not args.mmdet3d_infos:
        return "semantickitti"
    return "mmdet3d"


def run_export(args: argparse.Namespace) -> int:
    """`u4d export`: write the layout and print where a codebase's config points (data_root, ann_file)."""
    layout = chosen_layout(args)
    record = export_bank(args.bank, layout, args.out)
    if args.labels or args.mmdet3d_infos:
        logger.warning("--labels / --mmdet3d-infos are deprecated; this export is --layout %s", layout)
    data_root = args.bank if args.out is None else args.out
    scans = record["labels"]["files"]
    if layout == "pointcept":
        print(f"pointcept: {scans} scans in {data_root}/dataset/sequences (train split {', '.join(POINTCEPT_TRAIN)})")
        print(f"  data_root={data_root}; bank sequence -> Pointcept sequence in {data_root}/{EXPORT_RECORD}")
        return 0
    print(f"semantickitti: {scans} scans, labels all 0 (unlabeled), calib/poses/times in {data_root}/sequences")
    if layout == "mmdet3d":
        samples = record["mmdet3d_infos"]["samples"]
        print(f"mmdetection3d: data_root={data_root}, ann_file={INFOS_NAME} ({samples} samples)")
    return 0
