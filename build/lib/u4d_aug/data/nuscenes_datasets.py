"""Scan and L-frame window datasets over a nuScenes root: scenes are sequences, LIDAR_TOP sample_data tokens frames.

The items, `entries` and `label_set` are those of `u4d_aug.data.datasets.ScanDataset` / `SequenceDataset`; frames come
from the v1.0 tables (`u4d_aug.data.nuscenes`) in timestamp order, keyframes only unless `sweeps` (lidarseg labels
only keyframes). Source: ../shared/reference/segmentation_protocols.md §5.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from u4d_aug.data.formats import NuscenesScan, read_nuscenes_lidarseg, read_nuscenes_scan
from u4d_aug.data.labels import NUSCENES_LABELS, map_nuscenes
from u4d_aug.data.nuscenes import LIDAR_CHANNEL, NUSCENES_VERSION, LidarFrame, NuscenesIndex, read_nuscenes_index
from u4d_aug.errors import InputError

__all__ = ["NuscenesScanDataset", "NuscenesSequenceDataset", "resolve_scenes"]

PathLike = str | os.PathLike
_RANGE = re.compile(r"^(\d+)-(\d+)$")
_SPLIT_NAMES = ("train", "val", "test")  # SemanticKITTI split names, which a nuScenes root does not take


def resolve_scenes(index: NuscenesIndex, sequences: str | Sequence[str | int] | None) -> list[str]:
    """None -> every scene with LiDAR frames; else scene names, numbers (61 -> 'scene-0061') and ranges of scene
    numbers ('1-100': the scenes numbered 1..100 that exist), as one string or a list."""
    if sequences is None:
        return list(index.scenes)
    table = index.tables / "scene.json"
    numbered = {int(name[len("scene-") :]): name for name in index.scenes if re.fullmatch(r"scene-\d+", name)}
    names: list[str] = []
    for item in [sequences] if isinstance(sequences, str | int) else sequences:
        text = str(item)
        match = _RANGE.match(text)
        if match:
            first, last = (int(g) for g in match.groups())
            if last < first:
                raise InputError(f"sequences: range {text!r} ends before it starts")
            chosen = [numbered[n] for n in sorted(numbered) if first <= n <= last]
            if not chosen:
                raise InputError(f"{table}: no scene numbered {first}..{last} has {LIDAR_CHANNEL} frames")
            names += chosen
        elif text.isdigit():
            names.append(f"scene-{int(text):04d}")
        elif text in _SPLIT_NAMES:
            raise InputError(
                f"sequences={text!r} names a SemanticKITTI split; a nuScenes root takes scene names, numbers "
                "(61 = scene-0061) or ranges of them ('1-100')"
            )
        else:
            names.append(text)
    for name in names:
        if name not in index.scenes:
            shown = ", ".join(list(index.scenes)[:3]) + (", ..." if len(index.scenes) > 3 else "")
            raise InputError(f"{table}: no scene {name!r} with {LIDAR_CHANNEL} frames (scenes: {shown})")
    if not names:
        raise InputError(f"{index.root}: empty scene list")
    return list(dict.fromkeys(names))


class NuscenesScanDataset:
    """Single LIDAR_TOP scans of a nuScenes root; lidarseg labels mapped to train ids 0..15 (16 = ignore).

    item = dict(points (N, 4) float32 in the lidar frame, intensity / 255, labels (N,) int64 train ids or None,
    seq scene name, frame sample_data token). Keyframes only unless `sweeps`; returns within `remove_close` metres
    of the sensor (the ego car) are dropped with their labels (`read_nuscenes_scan`).
    """

    label_set = NUSCENES_LABELS

    def __init__(
        self,
        root: PathLike,
        sequences: str | Sequence[str | int] | None = None,
        labeled_only: bool = False,
        version: str = NUSCENES_VERSION,
        sweeps: bool = False,
        remove_close: float = 1.0,
    ) -> None:
        self.root = Path(root)
        self.index = read_nuscenes_index(self.root, version)
        self.sequences = resolve_scenes(self.index, sequences)
        self.remove_close = remove_close
        self.frames: dict[str, LidarFrame] = {f.token: f for seq in self.sequences for f in self.index.scenes[seq]}
        self.entries: list[tuple[str, str]] = [
            (seq, frame.token)
            for seq in self.sequences
            for frame in self.index.scenes[seq]
            if (sweeps or frame.is_key_frame) and (not labeled_only or frame.lidarseg is not None)
        ]

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, index: int) -> dict:
        seq, frame = self.entries[index]
        points, labels = self.load(seq, frame)
        return {"points": points, "labels": labels, "seq": seq, "frame": frame}

    def load(self, seq: str, frame: str) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (N, 4) and train ids (N,) (None for a frame without lidarseg) of sample_data `frame`."""
        scan = self._scan(seq, frame)
        record = self.frames[frame]
        if record.lidarseg is None:
            return scan.points, None
        label_path = self.root / record.lidarseg
        if not label_path.is_file():
            raise InputError(f"{label_path}: lidarseg file of sample_data {frame!r} (lidarseg.json) not found")
        raw = read_nuscenes_lidarseg(label_path, num_points=len(scan.keep))
        return scan.points, map_nuscenes(raw[scan.keep])

    def load_points(self, seq: str, frame: str) -> np.ndarray:
        """(N, 4) float32 points of one scan as items hold them (the rows of its probability file)."""
        return self._scan(seq, frame).points

    def _scan(self, seq: str, frame: str) -> NuscenesScan:
        path = self.root / self.frames[frame].filename
        if not path.is_file():
            raise InputError(f"{path}: scan file of sample_data {frame!r} (scene {seq}) not found")
        return read_nuscenes_scan(path, self.remove_close)

    def train_ids(self, index: int) -> np.ndarray | None:
        """(N,) int64 train ids of entry `index` (None without lidarseg)."""
        return self.load(*self.entries[index])[1]

    def pose(self, seq: str, frame: str) -> np.ndarray:
        """(4, 4) float64 lidar -> global pose of sample_data `frame` (ego_pose @ calibrated_sensor)."""
        return self.frames[frame].lidar_to_world


class NuscenesSequenceDataset:
    """Windows of `num_frames` LiDAR frames `stride` apart within one scene (keyframes, or every sweep with
    `sweeps`), posed relative to the first frame; items as `SequenceDataset`'s (poses T_0^-1 T_i, lidar frame)."""

    def __init__(
        self,
        root: PathLike,
        num_frames: int,
        sequences: str | Sequence[str | int] | None = None,
        stride: int = 1,
        with_poses: bool = True,
        version: str = NUSCENES_VERSION,
        sweeps: bool = False,
    ) -> None:
        if num_frames < 1 or stride < 1:
            raise InputError(f"num_frames and stride must be >= 1, got num_frames={num_frames}, stride={stride}")
        self.scans = NuscenesScanDataset(root, sequences, version=version, sweeps=sweeps)
        self.root, self.sequences = self.scans.root, self.scans.sequences
        self.num_frames, self.stride = num_frames, stride
        self.frames: dict[str, list[str]] = {seq: [] for seq in self.sequences}
        for seq, frame in self.scans.entries:
            self.frames[seq].append(frame)
        self.poses = (
            {seq: np.stack([self.scans.pose(seq, f) for f in self.frames[seq]]) for seq in self.sequences}
            if with_poses
            else None
        )
        span = (num_frames - 1) * stride + 1
        self.windows: list[tuple[str, int]] = [
            (seq, start) for seq in self.sequences for start in range(len(self.frames[seq]) - span + 1)
        ]
        if not self.windows:
            raise InputError(
                f"{self.root}: no scene has the {span} frames that a window of {num_frames} x stride {stride} needs"
            )

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, index: int) -> dict:
        seq, start = self.windows[index]
        positions = list(range(start, start + self.num_frames * self.stride, self.stride))
        frames = [self.frames[seq][i] for i in positions]
        loaded = [self.scans.load(seq, frame) for frame in frames]
        poses = None
        if self.poses is not None:
            absolute = self.poses[seq][positions]  # (L, 4, 4) lidar -> global
            poses = np.linalg.inv(absolute[0]) @ absolute  # (L, 4, 4) T_0^-1 T_i
        return {
            "points": [points for points, _ in loaded],
            "labels": [labels for _, labels in loaded],
            "poses": poses,
            "seq": seq,
            "frames": frames,
        }
