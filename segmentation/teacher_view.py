"""The teacher's view of unlabelled scans: the share of points the mean teacher keeps as pseudo-labels and their class
mix, pooled over scans (LaserMix's confidence threshold, `mean_teacher.pseudo_labels` with semi.pseudo_threshold).

Each scan is cut and augmented as the mean teacher's unlabelled stream does (`semi.load_unlabeled`: data.sector_deg,
data.max_points, the checkpoint's augment config) with a generator seeded by its position in the list, so two lists
of the same scans are seen alike. A source whose walls a segmentor cannot read keeps fewer labels and no buildings.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from segmentation.config import SegTrainConfig, class_names
from segmentation.data import augment, training_subset
from segmentation.mean_teacher import pseudo_labels
from segmentation.predict import load_checkpoint, model_from_checkpoint
from u4d_aug.config import saved_config
from u4d_aug.errors import InputError


def load_teacher(checkpoint: str | Path, device: torch.device | str = "cpu") -> tuple[SegTrainConfig, nn.Module]:
    """A segmentation checkpoint or exported weights -> (its training config, read also when saved before a key was
    removed (`saved_config`), and its net in eval mode on `device`)."""
    ckpt = load_checkpoint(checkpoint)
    cfg = saved_config(SegTrainConfig, ckpt["config"], source=f"{checkpoint} config")
    return cfg, model_from_checkpoint(ckpt, torch.device(device), source=str(checkpoint))


@torch.no_grad()
def teacher_logits(
    model: nn.Module, points: torch.Tensor, cfg: SegTrainConfig, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """(logits (N', K) float32, indices (N',) of the points it saw) of one scan (N, 4) cut and augmented as the mean
    teacher's unlabelled stream does (`semi.load_unlabeled`)."""
    keep = training_subset(points, cfg.data.sector_deg, cfg.data.max_points, generator)  # (N',)
    return model([augment(points[keep], generator, cfg.augment)]).float(), keep


def kept_class_counts(logits: torch.Tensor, cfg: SegTrainConfig) -> np.ndarray:
    """(K,) int64 points of each class the teacher keeps as pseudo-labels among logits (N, K)
    (`mean_teacher.pseudo_labels` at semi.pseudo_threshold and semi.pseudo_class_share)."""
    ignore = cfg.data.label_set.ignore_index
    labels, _ = pseudo_labels(logits, cfg.semi.pseudo_threshold, ignore, cfg.semi.pseudo_class_share)  # (N,)
    k = logits.shape[1]
    return np.bincount(labels[labels != ignore].cpu().numpy(), minlength=k)[:k]


def teacher_view(model: nn.Module, cfg: SegTrainConfig, scans: Iterable[np.ndarray | torch.Tensor]) -> dict:
    """Pooled over the scans (N_i, 4): {scans, points (seen), kept_share, class_share {name: share of the kept
    points}, building_share}; scan i is cut and augmented with a generator seeded i."""
    names = class_names(cfg)
    seen = 0
    kept = np.zeros(len(names), dtype=np.int64)
    count = 0
    for index, scan in enumerate(scans):
        generator = torch.Generator().manual_seed(index)
        logits, _ = teacher_logits(model, torch.as_tensor(scan, dtype=torch.float32), cfg, generator)
        seen += logits.shape[0]
        kept += kept_class_counts(logits, cfg)
        count += 1
    if seen == 0:
        raise InputError("teacher_view: the scans hold no point")
    share = kept / max(int(kept.sum()), 1)  # (K,)
    class_share = {name: float(value) for name, value in zip(names, share)}
    return {
        "scans": count,
        "points": seen,
        "kept_share": float(kept.sum()) / seen,
        "class_share": class_share,
        "building_share": class_share.get("building"),
    }
