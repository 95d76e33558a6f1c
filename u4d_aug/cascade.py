"""The hand-off of a two-level cascade: a layout scan of W/s columns becomes the condition of a detail net at W columns.

A layout net (the baseline, or U4D's one net) generates whole rings at a quarter of the columns, where a small net
sees the street corridor; a detail net (train-diffusion stage=detail) completes the full-width scan given those
columns, as stage 2 completes a scan given P_u: concat(x0_u, m) with m = the columns 0, s, 2s, … (cascaded diffusion
models, Ho et al. 2022; SR3, Saharia et al. 2022). In training the condition is the W/s-column projection of the
real scan, the very images the layout net learns, so the detail net reads what the layout net makes. Without a
detail net, the layout's columns are repeated s times (`upsample_nearest`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from u4d_aug.errors import InputError


def check_stride(width: int, stride: int, key: str = "detail_stride") -> int:
    """The layout width W / s of a detail net of `width` W columns and stride s; InputError naming the option `key`
    unless s >= 2 divides W."""
    if stride < 2 or width % stride:
        raise InputError(f"{key} must be >= 2 and divide width {width}, got {stride}")
    return width // stride


def place_columns(x_low: Tensor, stride: int) -> tuple[Tensor, Tensor]:
    """x_low (..., C, H, w) in [-1, 1] -> (x0_u (..., C, H, w·s): x_low at the columns 0, s, 2s, …, −1 elsewhere;
    m (..., 1, H, w·s): 1 on those columns), the detail net's condition."""
    if x_low.dim() < 3:
        raise InputError(f"x_low: expected a layout scan (..., C, H, w), got shape {tuple(x_low.shape)}")
    if stride < 2:
        raise InputError(f"detail_stride must be >= 2, got {stride}")
    *lead, channels, height, width = x_low.shape
    x0_u = torch.full((*lead, channels, height, width * stride), -1.0, dtype=x_low.dtype, device=x_low.device)
    x0_u[..., ::stride] = x_low
    m = torch.zeros((*lead, 1, height, width * stride), dtype=x_low.dtype, device=x_low.device)
    m[..., ::stride] = 1.0
    return x0_u, m


NEAREST = "nearest"  # `u4d generate detail=nearest`: the detail level without a net


def upsample_nearest(x_low: Tensor, stride: int) -> Tensor:
    """x_low (..., C, H, w) -> (..., C, H, w·s), each column repeated s times: the detail level without a net (the
    real scans' layouts come back this way with their teacher view and FPD nearly intact,
    benchmarks/results/generation/pilots.md)."""
    return x_low.repeat_interleave(stride, dim=-1)


def spread_columns(image: np.ndarray, stride: int) -> np.ndarray:
    """A layout-level side image (..., w) (stage 1's mask, x0_u) at the detail width (..., w·s): each column repeated
    s times, so it lies over the full-width scan it led to."""
    return np.repeat(image, stride, axis=-1)
