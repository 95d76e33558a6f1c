"""`u4d export BANK`: all-ignore SemanticKITTI labels and an mmdetection3d info file for any bank.

Labels: BANK/sequences/NN/labels/NNNNNN.label beside every velodyne/NNNNNN.bin, one uint32 per point of the .bin
(SemanticKITTI encoding: lower 16 bits semantic id, upper 16 instance id), all 0 = "unlabeled", which
SemanticKITTI-format loaders map to their ignore index (mmdetection3d labels_map 0 -> ignore, Pointcept
learning_map 0 -> ignore_index, LaserMix 0 = ignore). Without them Pointcept reads a scan without labels as class 0.

Info file: `semantickitti_infos_train.pkl`, plain python pickled, in the layout of mmdetection3d v1.4.0
(`tools/dataset_converters/semantickitti_converter.py::get_semantickitti_info`, read by
`mmdet3d/datasets/semantickitti_dataset.py` through `Seg3DDataset.parse_data_info`):
    {"metainfo": {"dataset": "SemanticKITTI"},
     "data_list": [{"lidar_points": {"lidar_path": "sequences/00/velodyne/000000.bin", "num_pts_feats": 4},
                    "pts_semantic_mask_path": "sequences/00/labels/000000.label",
                    "sample_idx": "00000000"}, ...]}
with paths relative to the bank (mmdetection3d's `data_root`). An entry names its label file only when it exists
(the converter's test split has none).

Label files are outside the per-sample digests of the manifest (`bank.sample_files` lists velodyne, mask,
uncertainty, stage1, empty, poses, calib), so a resumed `u4d generate` still finds every finished sample intact.
The manifest's "export" entry records what was written.
"""

from __future__ import annotations

import argparse
import logging
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from u4d_aug.bank import read_manifest, write_manifest
from u4d_aug.data.formats import label_path_for, write_kitti_label
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_bytes
from u4d_aug.runlock import run_lock

logger = logging.getLogger(__name__)

INFOS_NAME = "semantickitti_infos_train.pkl"
MMDET3D_VERSION = "1.4.0"  # the mmdetection3d release whose SemanticKITTI info layout `mmdet3d_infos` follows
POINT_BYTES = 16  # (x, y, z, intensity) float32
PICKLE_PROTOCOL = 4  # readable by every python 3 that mmdetection3d supports


def bank_scans(root: Path) -> list[Path]:
    """Every velodyne/*.bin of the bank's sequences, in sequence then frame order."""
    return sorted((Path(root) / "sequences").glob("*/velodyne/*.bin"))


def scan_point_count(path: Path) -> int:
    """Number of (x, y, z, intensity) float32 records of a KITTI .bin (the count every loader reads, NaN rows too)."""
    size = path.stat().st_size
    if size % POINT_BYTES:
        raise InputError(f"{path}: {size} bytes is not a whole number of 16-byte points (truncated scan)")
    return size // POINT_BYTES


def write_ignore_labels(scan: Path) -> bool:
    """Write the all-0 ("unlabeled") .label of `scan` unless one with a label per point is there; True if written."""
    label = label_path_for(scan)
    count = scan_point_count(scan)
    if label.is_file() and label.stat().st_size == 4 * count:
        return False
    if label.is_file():
        labels = label.stat().st_size // 4
        logger.warning("%s: %d labels for %d points (scan written again since); rewriting", label, labels, count)
    write_kitti_label(label, np.zeros(count, dtype=np.uint16))
    return True


def mmdet3d_infos(root: Path, scans: list[Path]) -> dict[str, Any]:
    """The info dict of mmdetection3d v1.4.0's SemanticKITTI converter for `scans` (paths relative to `root`)."""
    data_list = []
    for scan in scans:
        sequence = scan.parent.parent.name
        entry: dict[str, Any] = {
            "lidar_points": {"lidar_path": scan.relative_to(root).as_posix(), "num_pts_feats": 4},
        }
        label = label_path_for(scan)
        if label.is_file():
            entry["pts_semantic_mask_path"] = label.relative_to(root).as_posix()
        entry["sample_idx"] = f"{sequence}{scan.stem}"
        data_list.append(entry)
    return {"metainfo": {"dataset": "SemanticKITTI"}, "data_list": data_list}


def export_bank(root: str | Path, labels: bool, infos: bool, out: str | Path | None = None) -> dict[str, Any]:
    """Write the label files and/or the info file of a bank; returns the manifest's "export" record."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: not a bank (no such folder)")
    manifest = read_manifest(root)
    if manifest is None:
        raise InputError(f"{root}: not a bank (no manifest.json; `u4d generate --out` writes one)")
    with run_lock(root):  # not while `u4d generate` writes this bank
        scans = bank_scans(root)
        record = dict(manifest.get("export") or {})
        if labels:
            written = sum(write_ignore_labels(scan) for scan in scans)
            record["labels"] = {"files": len(scans), "semantic": 0, "instance": 0}
            logger.info("%s: %d label files written, %d already there", root, written, len(scans) - written)
        if infos:
            folder = root if out is None else Path(out)
            path = folder / INFOS_NAME
            atomic_write_bytes(path, pickle.dumps(mmdet3d_infos(root, scans), protocol=PICKLE_PROTOCOL))
            where = path.relative_to(root).as_posix() if path.is_relative_to(root) else str(path.resolve())
            record["mmdet3d_infos"] = {"path": where, "samples": len(scans), "mmdet3d_version": MMDET3D_VERSION}
        if record != manifest.get("export"):
            write_manifest(root, {**manifest, "export": record})  # samples and their digests unchanged
    return record


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d export BANK [--labels] [--mmdet3d-infos] [--out DIR]`."""
    parser.add_argument("bank", type=Path, help="a bank written by `u4d generate`")
    parser.add_argument(
        "--labels", action="store_true", help="all-ignore labels/NNNNNN.label (value 0) beside every velodyne scan"
    )
    parser.add_argument(
        "--mmdet3d-infos", action="store_true", help=f"{INFOS_NAME} for mmdetection3d's SemanticKittiDataset"
    )
    parser.add_argument("--out", type=Path, default=None, help="folder of the info file (default: the bank)")


def run_export(args: argparse.Namespace) -> int:
    """`u4d export`: with neither --labels nor --mmdet3d-infos both are written."""
    labels, infos = args.labels, args.mmdet3d_infos
    if not labels and not infos:
        labels = infos = True
    record = export_bank(args.bank, labels, infos, args.out)
    if labels:
        print(f"labels: {record['labels']['files']} files (all 0 = unlabeled) in {args.bank}/sequences/*/labels")
    if infos:
        print(f"mmdetection3d infos: {record['mmdet3d_infos']['path']} ({record['mmdet3d_infos']['samples']} samples)")
    return 0
