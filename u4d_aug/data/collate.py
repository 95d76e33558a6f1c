"""Batches of variable-size scans the way sparse-convolution codebases take them (Pointcept, MinkowskiEngine).

Scans are concatenated, each point carries its scan's index, and `offsets` (B+1,) marks where scan b starts
(b < B) and where the batch ends (b = B), the convention of `u4d_aug.range_view.project_batch`. Use
`collate_scans` as a `DataLoader`'s `collate_fn` over `ScanDataset` (a labelled root or a bank) or
`GeneratedScans`; `split_points` gives the list of (N_b, 4) scans back (what `segmentation.models` take).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from u4d_aug.data.labels import SEMANTICKITTI_IGNORE
from u4d_aug.errors import InputError

__all__ = ["collate_scans", "split_points"]


def collate_scans(items: Sequence[dict], ignore_index: int = SEMANTICKITTI_IGNORE) -> dict:
    """Items {points (N_b, 4), labels (N_b,) | None, seq, frame} -> one batch of B scans.

    batch = {points (N, 4) float32, labels (N,) int64 or None, batch_index (N,) int64, offsets (B+1,) int64,
    seq [B] str, frame [B] str}, N = sum N_b. labels is None when no scan has labels; when only some have
    (a labelled root with unlabelled frames, a bank mixed with real scans), the others' points get `ignore_index`.
    A malformed item (no seq/frame, points not (N, 4), labels not one integer per point) is an InputError naming it.
    """
    if len(items) == 0:
        raise InputError("collate_scans: items is empty; expected at least one scan")
    points = [_item_points(item, b) for b, item in enumerate(items)]
    counts = torch.tensor([len(p) for p in points], dtype=torch.int64)
    labels = None
    if any(item.get("labels") is not None for item in items):
        labels = torch.cat(
            [_item_labels(item, b, len(p), ignore_index) for b, (item, p) in enumerate(zip(items, points))]
        )
    return {
        "points": torch.cat(points),  # (N, 4)
        "labels": labels,  # (N,) or None
        "batch_index": torch.repeat_interleave(torch.arange(len(points)), counts),  # (N,)
        "offsets": torch.cat([counts.new_zeros(1), counts.cumsum(0)]),  # (B+1,)
        "seq": [str(item["seq"]) for item in items],
        "frame": [str(item["frame"]) for item in items],
    }


def _item_points(item: object, b: int) -> torch.Tensor:
    """items[b]'s (N_b, 4) float32 points, after checking it is a dict with the keys a batch needs."""
    if not isinstance(item, dict):
        raise InputError(f"collate_scans: items[{b}] is a {type(item).__name__}; expected a dict (points, seq, frame)")
    missing = [key for key in ("points", "seq", "frame") if key not in item]
    if missing:
        raise InputError(f"collate_scans: items[{b}] has no {', '.join(missing)}; expected keys points, seq, frame")
    points = np.asarray(item["points"])
    if points.ndim != 2 or points.shape[1] != 4 or points.dtype.kind not in "fiu":
        raise InputError(
            f"collate_scans: items[{b}]['points'] has shape {points.shape} {points.dtype}; expected (N, 4) numbers"
        )
    return torch.as_tensor(points.astype(np.float32, copy=False))


def _item_labels(item: dict, b: int, count: int, ignore_index: int) -> torch.Tensor:
    """items[b]'s (N_b,) int64 labels (`ignore_index` without any): one integer per point, never truncated floats."""
    if item.get("labels") is None:
        return torch.full((count,), ignore_index, dtype=torch.int64)
    labels = np.asarray(item["labels"])
    if labels.dtype.kind not in "iu":
        raise InputError(
            f"collate_scans: items[{b}]['labels'] are {labels.dtype}; expected integer class ids (not truncated)"
        )
    if labels.shape != (count,):
        raise InputError(
            f"collate_scans: items[{b}]['labels'] has shape {labels.shape}; expected ({count},), one per point"
        )
    return torch.as_tensor(labels.astype(np.int64, copy=False))


def split_points(batch: dict) -> list[torch.Tensor]:
    """The batch's scans again: a list of B (N_b, 4) views of `batch["points"]`."""
    offsets = batch["offsets"].tolist()
    return [batch["points"][start:end] for start, end in zip(offsets[:-1], offsets[1:])]
