"""One scan from any supported file, as the library uses it: points, train-id labels, sensor and ignore id.

SemanticKITTI `.bin` (its `.label` found in `labels/` beside `velodyne/`, or beside the scan) and nuScenes
`.pcd.bin` (with the `_lidarseg.bin` passed as `label_path`); formats in `u4d_aug.data.formats`, label maps in
`u4d_aug.data.labels` (raw ids become train ids here, once).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from u4d_aug.data.formats import (
    label_path_for,
    load_kitti_frame,
    read_nuscenes_lidarseg,
    read_nuscenes_scan,
)
from u4d_aug.data.labels import NUSCENES_IGNORE, SEMANTICKITTI_IGNORE, map_nuscenes, map_semantickitti

__all__ = ["Scan", "read_scan"]


@dataclass
class Scan:
    """Points (N, 4) float32 [x, y, z, intensity in [0, 1]], train ids (N,) int64 or None, sensor, ignore id."""

    points: np.ndarray
    labels: np.ndarray | None
    sensor: str  # "hdl64" (SemanticKITTI) | "hdl32" (nuScenes)
    ignore_index: int  # 19 (SemanticKITTI) | 16 (nuScenes)


def read_scan(path: str | os.PathLike, label_path: str | os.PathLike | None = None) -> Scan:
    """Read a SemanticKITTI `.bin` or a nuScenes `.pcd.bin`; labels from `label_path` or, for KITTI, beside it."""
    path = Path(path)
    if path.name.endswith(".pcd.bin"):
        scan = read_nuscenes_scan(path)
        labels = None
        if label_path is not None:
            raw = read_nuscenes_lidarseg(label_path, num_points=len(scan.keep))
            labels = map_nuscenes(raw[scan.keep])
        return Scan(scan.points, labels, "hdl32", NUSCENES_IGNORE)
    if label_path is None and label_path_for(path).is_file():
        label_path = label_path_for(path)
    frame = load_kitti_frame(path, label_path)
    labels = map_semantickitti(frame.semantic) if frame.semantic is not None else None
    return Scan(frame.points, labels, "hdl64", SEMANTICKITTI_IGNORE)
