"""Scans for segmentation training: label splits (uniform / sequence-disjoint), augmentation, batching."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json

FrameId = tuple[str, str]  # (sequence, frame), e.g. ("00", "000123")


@dataclass
class AugmentConfig:
    """Scan augmentation as the LaserMix MinkUNet config: rotation about z, flips, scaling, jitter.

    paste_prob > 0 adds PolarMix's instance-level rotate-pasting (Xiao et al., NeurIPS 2022): with that
    probability a labeled training scan receives the points of the `paste_classes` (train-id names) of another
    random training scan, as `paste_copies` copies rotated about z by random angles (labels kept). The names are
    checked against the data's label set by `SegTrainConfig`, which also fills in the default.
    """

    rotate: bool = True
    flip: bool = True
    scale_min: float = 0.95
    scale_max: float = 1.05
    jitter_std: float = 0.01
    paste_prob: float = 0.0
    # null = the label set's thing classes (SemanticKITTI: bicycle .. motorcyclist; car is common enough)
    paste_classes: list[str] | None = None
    paste_copies: int = 2

    def __post_init__(self) -> None:
        if not 0.0 <= self.paste_prob <= 1.0 or self.paste_copies < 1:
            raise ValueError("augment.paste_prob must be in [0, 1] and augment.paste_copies >= 1")


def paste_instances(
    points: torch.Tensor,
    labels: torch.Tensor,
    source_points: torch.Tensor,
    source_labels: torch.Tensor,
    class_ids: torch.Tensor,
    copies: int,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """PolarMix instance-level rotate-pasting: append the source points whose label is in class_ids, `copies`
    times, each copy rotated about z by an angle drawn uniformly in [0, 2 pi) (Xiao et al. 2022, Sec. 3.2).

    points (N, 4), labels (N,); source_points (M, 4), source_labels (M,) -> (N + copies * M_sel, 4), labels.
    """
    chosen = torch.isin(source_labels, class_ids)
    angles = torch.rand(copies, generator=generator, dtype=torch.float64) * 2.0 * math.pi
    if not bool(chosen.any()):
        return points, labels
    picked, picked_labels = source_points[chosen], source_labels[chosen]
    out_points, out_labels = [points], [labels]
    for angle in angles.tolist():
        c, s = math.cos(angle), math.sin(angle)
        copy = picked.clone()
        copy[:, 0] = c * picked[:, 0] - s * picked[:, 1]
        copy[:, 1] = s * picked[:, 0] + c * picked[:, 1]
        out_points.append(copy)
        out_labels.append(picked_labels)
    return torch.cat(out_points), torch.cat(out_labels)


def augment(points: torch.Tensor, generator: torch.Generator, cfg: AugmentConfig) -> torch.Tensor:
    """Random rigid-ish transform of one scan (N, 4): rotate about z, flip x/y, scale, jitter xyz."""
    xyz = points[:, :3]
    angle = float(torch.rand((), generator=generator)) * 2.0 * math.pi if cfg.rotate else 0.0
    c, s = math.cos(angle), math.sin(angle)
    rotation = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=points.dtype)
    if cfg.flip:
        flips = torch.rand(2, generator=generator) < 0.5
        rotation = rotation @ torch.diag(
            torch.tensor([-1.0 if flips[0] else 1.0, -1.0 if flips[1] else 1.0, 1.0], dtype=points.dtype)
        )
    scale = cfg.scale_min + float(torch.rand((), generator=generator)) * (cfg.scale_max - cfg.scale_min)
    xyz = (xyz @ rotation.T.to(xyz.device)) * scale
    if cfg.jitter_std > 0:
        noise = torch.randn(xyz.shape, generator=generator, dtype=xyz.dtype) * cfg.jitter_std
        xyz = xyz + noise.to(xyz.device)
    return torch.cat([xyz, points[:, 3:]], dim=1)


def training_subset(
    points: torch.Tensor, sector_deg: float | None, max_points: int | None, generator: torch.Generator
) -> torch.Tensor:
    """Indices (N',) of the training part of one scan (N, 4): a random azimuth sector, then a random subset.

    The sector (sector_deg < 360) keeps every point whose azimuth lies within sector_deg degrees after a start
    angle drawn uniformly: cheaper steps that keep the point density the evaluation sees, unlike random thinning
    (0.2 m voxels of a 122k-point sim scan: a 90-degree sector keeps 8.8k of 33k voxels, thinning to 12k points
    8.7k, emptying the far voxels and lightening the near ones). An empty sector keeps the whole scan. Then at
    most max_points of the kept points, uniformly at random (max_points None = all).
    """
    keep = torch.arange(points.shape[0])
    if sector_deg is not None and sector_deg < 360.0:
        start = float(torch.rand((), generator=generator)) * 2.0 * math.pi
        azimuth = torch.atan2(points[:, 1], points[:, 0]).double()  # (N,) in [-pi, pi]
        inside = torch.remainder(azimuth - start, 2.0 * math.pi) < math.radians(sector_deg)
        if bool(inside.any()):
            keep = keep[inside]
    if max_points is not None and keep.numel() > max_points:
        keep = keep[torch.randperm(keep.numel(), generator=generator)[:max_points]]
    return keep


def make_split(
    frames: list[FrameId],
    fraction: float,
    seed: int,
    mode: Literal["uniform", "sequence"] = "uniform",
) -> tuple[list[FrameId], list[FrameId]]:
    """Labeled / unlabeled split of a train set (LaserMix track 1 'uniform', or whole sequences labeled)."""
    if not 0.0 < fraction <= 1.0:
        raise InputError(f"split fraction must be in (0, 1], got {fraction}")
    if not frames:
        raise InputError("cannot split an empty list of frames")
    rng = np.random.default_rng(seed)
    if fraction >= 1.0:
        # "Full": the whole train set is both the labeled and the unlabeled set (LaserMix issue #34).
        return list(frames), list(frames)
    if mode == "uniform":
        count = max(1, round(fraction * len(frames)))
        chosen = set(rng.choice(len(frames), size=count, replace=False).tolist())
    elif mode == "sequence":
        sequences = sorted({seq for seq, _ in frames})
        order = rng.permutation(len(sequences))
        target = fraction * len(frames)
        chosen_seqs: set[str] = set()
        labeled_count = 0
        for index in order:
            if labeled_count >= target and chosen_seqs:
                break
            seq = sequences[index]
            chosen_seqs.add(seq)
            labeled_count += sum(1 for s, _ in frames if s == seq)
        chosen = {i for i, (seq, _) in enumerate(frames) if seq in chosen_seqs}
    else:
        raise ValueError(f"split mode must be 'uniform' or 'sequence', got {mode!r}")
    labeled = [f for i, f in enumerate(frames) if i in chosen]
    unlabeled = [f for i, f in enumerate(frames) if i not in chosen]
    return labeled, unlabeled


def frames_digest(frames: list[FrameId]) -> str:
    """Eight hex digits naming a train set (sha1 of its sorted frame ids): two train sets never share a split."""
    text = "\n".join(f"{seq}/{frame}" for seq, frame in sorted(frames))
    return hashlib.sha1(text.encode()).hexdigest()[:8]


def split_path(out: Path, frames: list[FrameId], fraction: float, seed: int, mode: str) -> Path:
    """Where a run keeps its split: OUT/splits/<mode>_<percent>pct_seed<seed>_<frames digest>.json (never in the
    data root, which may be a read-only mount or another user's dataset)."""
    percent = f"{100.0 * fraction:g}".replace(".", "p")
    return Path(out) / "splits" / f"{mode}_{percent}pct_seed{seed}_{frames_digest(frames)}.json"


def load_or_make_split(
    out: Path, frames: list[FrameId], fraction: float, seed: int, mode: Literal["uniform", "sequence"]
) -> tuple[list[FrameId], list[FrameId]]:
    """Reuse the run's split file (OUT/splits) when it matches these frames, else draw it and write it there; the
    draw depends on (frames, fraction, seed, mode) only, so every arm of an experiment gets the same split."""
    path = split_path(out, frames, fraction, seed, mode)
    if path.is_file():
        try:
            data = json.loads(path.read_text())
            labeled = [tuple(x) for x in data["labeled"]]
            unlabeled = [tuple(x) for x in data["unlabeled"]]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise InputError(f"{path}: not a split file (expected json with 'labeled' and 'unlabeled')") from None
        if set(labeled) | set(unlabeled) == set(frames):
            return labeled, unlabeled
    labeled, unlabeled = make_split(frames, fraction, seed, mode)
    atomic_write_json(
        path,
        {"fraction": fraction, "seed": seed, "mode": mode, "labeled": labeled, "unlabeled": unlabeled},
    )
    return labeled, unlabeled
