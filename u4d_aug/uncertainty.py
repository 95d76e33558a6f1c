"""Point-wise predictive uncertainty and the uncertain region P_u projected to (x0_u, m_u) (U4D paper §2.1).

H(p) = −Σ_k p_k log p_k per point from the segmentation net's class probabilities (`u4d seg-predict` writes
PROBS/sequences/XX/probs/NNNNNN.npy, float16 (N, K) in the scan's point order); the top-K points form P_u.
Strategies for the paper's ablation: `entropy` (default), `confidence` (lowest max-probability), `random`, `none`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from u4d_aug.data.sensors import Sensor
from u4d_aug.errors import InputError
from u4d_aug.io import load_npy
from u4d_aug.range_view import RowMode, project, scatter_to_image, to_image

Strategy = Literal["entropy", "confidence", "random", "none"]
STRATEGIES: tuple[str, ...] = ("entropy", "confidence", "random", "none")


def probs_path(probs_root: str | Path, seq: str, frame: str) -> Path:
    """PROBS/sequences/XX/probs/NNNNNN.npy (the contract of `u4d seg-predict`)."""
    return Path(probs_root) / "sequences" / seq / "probs" / f"{frame}.npy"


def load_probs(path: str | Path, num_points: int | None = None) -> np.ndarray:
    """Read a float16/float32 (N, K) probability file; check N against the scan when given."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: probability file not found (write it with `u4d seg-predict`)")
    probs = load_npy(path, "probability file")
    if probs.ndim != 2 or probs.shape[1] < 1 or probs.dtype.kind != "f":
        raise InputError(
            f"{path}: expected an (N, K) float array of class probabilities, got shape {probs.shape} {probs.dtype}"
        )
    if num_points is not None and probs.shape[0] != num_points:
        raise InputError(f"{path}: has {probs.shape[0]} rows but the scan has {num_points} points")
    bad = int(np.count_nonzero(~np.isfinite(probs)))
    if bad:
        raise InputError(f"{path}: {bad} probabilities are NaN/inf; expected values in [0, 1]")
    check_probabilities(probs, str(path))
    return probs


# float16 files: each value within 1e-3 of [0, 1], each row's sum within 1e-2 of 1 (K rounding errors of 2^-11)
VALUE_TOLERANCE, SUM_TOLERANCE = 1e-3, 1e-2


def check_probabilities(probs: np.ndarray, source: str) -> None:
    """InputError unless every value of the (N, K) array is in [0, 1] and every row sums to 1 (within the
    tolerances): logits or scores passed as probabilities would give negative or meaningless entropies."""
    values = probs.astype(np.float32, copy=False)
    outside = int(np.count_nonzero((values < -VALUE_TOLERANCE) | (values > 1 + VALUE_TOLERANCE)))
    if outside:
        low, high = float(values.min()), float(values.max())
        raise InputError(
            f"{source}: {outside} values outside [0, 1] (min {low:.4g}, max {high:.4g}); expected class "
            "probabilities (softmax), not logits"
        )
    sums = values.sum(axis=1)
    off = np.abs(sums - 1.0) > SUM_TOLERANCE
    if off.any():
        worst = float(sums[np.argmax(np.abs(sums - 1.0))])
        raise InputError(
            f"{source}: {int(off.sum())} of {len(sums)} rows do not sum to 1 (e.g. {worst:.4g}); expected class "
            "probabilities (softmax) per point"
        )


def entropy(probs: Tensor | np.ndarray) -> Tensor:
    """Shannon entropy H = −Σ p log p (nats) per row of (N, K) probabilities, with 0·log 0 = 0 → (N,) float32.

    NaN/inf probabilities are refused (InputError): they would make an arbitrary region the uncertain one.
    """
    p = torch.as_tensor(probs).float()  # float16 files: compute in float32
    if not bool(torch.isfinite(p).all()):
        raise InputError(f"probabilities hold {int((~torch.isfinite(p)).sum())} NaN/inf values; expected [0, 1]")
    outside = int(((p < -VALUE_TOLERANCE) | (p > 1 + VALUE_TOLERANCE)).sum())
    if outside:
        raise InputError(f"probabilities hold {outside} values outside [0, 1]; expected softmax outputs, not logits")
    p = p.clamp(0.0, 1.0)
    return -torch.special.xlogy(p, p).sum(dim=-1)


def _num_selected(k: int | float, num_points: int) -> int:
    if isinstance(k, bool):
        raise InputError(f"uncertainty k must be a point count (int) or a fraction (float), got {k!r}")
    if isinstance(k, int):
        if k < 0:
            raise InputError(f"uncertainty k as a count must be >= 0, got {k}")
        return min(k, num_points)
    if not 0.0 <= float(k) <= 1.0:
        raise InputError(f"uncertainty k as a fraction must be in [0, 1], got {k}")
    return int(round(float(k) * num_points))


def select_uncertain(
    probs: Tensor | np.ndarray,
    k: int | float,
    strategy: Strategy = "entropy",
    generator: torch.Generator | None = None,
) -> Tensor:
    """Indices (K,) int64 of P_u: the K most uncertain points (int k: a count; float k: a fraction of N).

    entropy: highest H(p); confidence: lowest max_k p_k; random: uniform without replacement (needs
    `generator`); none: empty (the ablation without an uncertain region). Ties go to the lower index.
    """
    p = torch.as_tensor(probs)
    if p.ndim != 2:
        raise InputError(f"probs must have shape (N, K), got {tuple(p.shape)}")
    num_points = p.shape[0]
    count = _num_selected(k, num_points)
    if strategy == "none" or count == 0:
        return torch.zeros(0, dtype=torch.int64)
    if strategy == "entropy":
        score = entropy(p)  # (N,) higher = more uncertain
    elif strategy == "confidence":
        score = -p.float().max(dim=1).values  # (N,) lower max-probability = more uncertain
    elif strategy == "random":
        if generator is None:
            raise ValueError("select_uncertain(strategy='random') needs a torch.Generator")
        return torch.randperm(num_points, generator=generator)[:count].sort().values
    else:
        raise InputError(f"uncertainty strategy {strategy!r} is not one of {', '.join(STRATEGIES)}")
    order = torch.argsort(score, descending=True, stable=True)
    return order[:count].sort().values


def uncertain_range_view(
    points: Tensor | np.ndarray,
    probs: Tensor | np.ndarray,
    sensor: Sensor,
    height: int | None = None,
    width: int | None = None,
    row_mode: RowMode = "beam",
    k: int | float = 0.1,
    strategy: Strategy = "entropy",
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """P_u projected: x0_u (2, H, W) in [-1, 1] (−1 off P_u), m_u (1, H, W) float {0, 1}, entropy image (H, W).

    Both come from the projection of the full scan: m_u marks the pixels whose shown (nearest) point is in P_u and
    x0_u is the full scan's image x0 there, so x0_u = x0 · m_u exactly (−1 elsewhere) and stage 2 is conditioned on
    what the full-scan image holds, not on P_u points that a nearer point hides. The entropy image shows H(p) of the
    point that wins each pixel in the full scan (NaN where no return); it is the uncertainty map of the figures and
    of the generated banks.
    """
    points_t = torch.as_tensor(points).float()
    probs_t = torch.as_tensor(probs)
    if probs_t.ndim != 2 or probs_t.shape[0] != points_t.shape[0]:
        raise InputError(
            f"probs must have shape (N, K) with N = {points_t.shape[0]} points of the scan, got {tuple(probs_t.shape)}"
        )
    height = sensor.height if height is None else height
    width = sensor.width if width is None else width
    selected = select_uncertain(probs_t, k, strategy, generator)  # (K,)
    projection = project(points_t, sensor, height, width, row_mode)
    x0 = to_image(projection, sensor)  # (2, H, W)
    in_p_u = torch.zeros(points_t.shape[0], dtype=torch.bool)
    in_p_u[selected] = True
    m_u = scatter_to_image(in_p_u, projection, fill=False).unsqueeze(0).float()  # (1, H, W)
    x0_u = torch.where(m_u.bool(), x0, torch.full_like(x0, -1.0))
    entropy_image = scatter_to_image(entropy(probs_t), projection, fill=float("nan"))  # (H, W)
    return x0_u, m_u, entropy_image
