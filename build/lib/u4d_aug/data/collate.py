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

__all__ = ["collate_scans", "split_points"]


def collate_scans(items: Sequence[dict], ignore_index: int = SEMANTICKITTI_IGNORE) -> dict:
    """Items {points (N_b, 4), labels (N_b,) | None, seq, frame} -> one batch of B scans.

    batch = {points (N, 4) float32, labels (N,) int64 or None, batch_index (N,) int64, offsets (B+1,) int64,
    seq [B] str, frame [B] str}, N = sum N_b. labels is None when no scan has labels; when only some have
    (a labelled root with unlabelled frames, a bank mixed with real scans), the others' points get `ignore_index`.
    """
    if len(items) == 0:
        raise ValueError("collate_scans needs at least one scan")
    points = [torch.as_tensor(np.asarray(item["points"], dtype=np.float32)) for item in items]
    for b, p in enumerate(points):
        if p.ndim != 2 or p.shape[1] != 4:
            raise ValueError(f"collate_scans: scan {b} has points of shape {tuple(p.shape)}, expected (N, 4)")
    counts = torch.tensor([len(p) for p in points], dtype=torch.int64)
    labels = None
    if any(item.get("labels") is not None for item in items):
        labels = torch.cat(
            [
                torch.full((len(p),), ignore_index, dtype=torch.int64)
                if item.get("labels") is None
                else torch.as_tensor(np.asarray(item["labels"]), dtype=torch.int64)
                for item, p in zip(items, points)
            ]
        )
        if len(labels) != int(counts.sum()):
            raise ValueError("collate_scans: a scan has a different number of labels than points")
    return {
        "points": torch.cat(points),  # (N, 4)
        "labels": labels,  # (N,) or None
        "batch_index": torch.repeat_interleave(torch.arange(len(points)), counts),  # (N,)
        "offsets": torch.cat([counts.new_zeros(1), counts.cumsum(0)]),  # (B+1,)
        "seq": [str(item["seq"]) for item in items],
        "frame": [str(item["frame"]) for item in items],
    }


def split_points(batch: dict) -> list[torch.Tensor]:
    """The batch's scans again: a list of B (N_b, 4) views of `batch["points"]`."""
    offsets = batch["offsets"].tolist()
    return [batch["points"][start:end] for start, end in zip(offsets[:-1], offsets[1:])]
