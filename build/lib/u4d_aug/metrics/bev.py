"""BEV occupancy metrics, R2DM protocol (`metrics/bev.py`, a port of LiDARGen): histograms, JSD, Gaussian MMD.

Per scan: keep points inside the 0.5-63 m evaluation window (R2DM `MIN_DEPTH`/`MAX_DEPTH`, from LiDARGen),
then 3 < ||p|| < 70 m, and count (x, y) in a 100 x 100 grid over [-80, 80]^2 m (1.6 m cells).
JSD: scipy `jensenshannon` (a distance = sqrt of the divergence, natural log) between the pooled pmfs.
MMD: Gaussian RBF (sigma = 0.5) on per-scan normalised, flattened histograms, biased V-statistic; the papers
print it in units of 1e-4, so report `value * MMD_REPORT_SCALE`.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from scipy.spatial.distance import jensenshannon

from u4d_aug.errors import InputError

EVAL_MIN_DEPTH = 0.5  # m, R2DM/LiDARGen evaluation window applied to real and generated scans
EVAL_MAX_DEPTH = 63.0
BEV_MIN_DEPTH = 3.0  # m, histogram mask (R2DM point_cloud_to_histogram, "from lidargen")
BEV_MAX_DEPTH = 70.0
BEV_FIELD_SIZE = 160.0  # m, grid covers [-80, 80]^2
BEV_BINS = 100
MMD_SIGMA = 0.5
MMD_REPORT_SCALE = 1e4  # papers print MMD in units of 1e-4: reported = raw * MMD_REPORT_SCALE


def bev_histogram(points: np.ndarray, bins: int = BEV_BINS, field_size: float = BEV_FIELD_SIZE) -> np.ndarray:
    """(bins, bins) float32 counts of (x, y), 3 < ||p|| < 70 m within the 0.5-63 m window (R2DM/LiDARGen)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(f"bev_histogram: expected points of shape (N, >=3), got {points.shape}")
    xy = points[:, :2].astype(np.float64)  # (N, 2)
    z = points[:, 2].astype(np.float64)  # (N,)
    depth2 = xy[:, 0] ** 2 + xy[:, 1] ** 2 + z**2  # squared range, no sqrt needed for the masks
    keep = (depth2 >= EVAL_MIN_DEPTH**2) & (depth2 <= EVAL_MAX_DEPTH**2)
    keep &= (depth2 > BEV_MIN_DEPTH**2) & (depth2 < BEV_MAX_DEPTH**2)
    bound = field_size / 2.0
    # Bins of torch.histogramdd(range=[-b, b, -b, b]): half-open cells, the upper edge goes to the last one.
    cell = np.floor((xy[keep] + bound) * (bins / field_size)).astype(np.int64)  # (M, 2) x bin, y bin
    cell[xy[keep] == bound] = bins - 1
    inside = ((cell >= 0) & (cell < bins)).all(axis=1)
    flat = cell[inside, 0] * bins + cell[inside, 1]  # row = x bin, column = y bin, as histogramdd
    return np.bincount(flat, minlength=bins * bins).reshape(bins, bins).astype(np.float32)


def bev_histograms(scans: Iterable[np.ndarray], bins: int = BEV_BINS) -> np.ndarray:
    """Stack `bev_histogram` over scans -> (S, bins, bins) float32."""
    hists = [bev_histogram(points, bins=bins) for points in scans]
    if not hists:
        raise InputError("bev_histograms: no scans given")
    return np.stack(hists)


def _as_histograms(hists: np.ndarray, name: str) -> np.ndarray:
    """(S, H, W) or (H, W) -> (S, H*W) float64, non-negative."""
    hists = np.asarray(hists, dtype=np.float64)
    if hists.ndim == 2:
        hists = hists[None]
    if hists.ndim != 3 or hists.shape[0] == 0:
        raise InputError(f"{name}: expected histograms of shape (S, H, W) or (H, W), got {hists.shape}")
    if not np.isfinite(hists).all() or (hists < 0).any():
        raise InputError(f"{name}: histograms must be finite and non-negative")
    return hists.reshape(hists.shape[0], -1)


def bev_jsd(hists_a: np.ndarray, hists_b: np.ndarray) -> float:
    """Jensen-Shannon distance (natural log, in [0, sqrt(ln 2)]) of pooled pmfs (R2DM `compute_jsd_2d`)."""
    a = _as_histograms(hists_a, "hists_a").sum(axis=0)  # (H*W,)
    b = _as_histograms(hists_b, "hists_b").sum(axis=0)
    if a.shape != b.shape:
        raise InputError(f"bev_jsd: histogram sizes differ, {a.shape} vs {b.shape}")
    if a.sum() == 0 or b.sum() == 0:
        raise InputError("bev_jsd: a histogram set has no points in the 3-63 m window")
    return float(jensenshannon(a / a.sum(), b / b.sum()))


def _normalised(hists: np.ndarray, name: str) -> torch.Tensor:
    """Per-scan pmfs (S, H*W) float64; an empty scan has no pmf, so it is refused."""
    flat = _as_histograms(hists, name)
    totals = flat.sum(axis=1, keepdims=True)  # (S, 1)
    empty = np.flatnonzero(totals[:, 0] == 0)
    if empty.size:
        raise InputError(f"{name}: scan {int(empty[0])} has no points in the 3-63 m window ({empty.size} empty)")
    return torch.from_numpy(flat / totals)


def _mean_rbf(p: torch.Tensor, q: torch.Tensor, gamma: float) -> float:
    """mean_ij exp(-gamma ||p_i - q_j||^2) by one matmul (float64: near-1 kernel values keep their digits)."""
    sq = (p * p).sum(1)[:, None] + (q * q).sum(1)[None, :] - 2.0 * (p @ q.T)  # (S_p, S_q)
    return float(torch.exp(-gamma * sq.clamp_min(0.0)).mean())


def bev_mmd(hists_a: np.ndarray, hists_b: np.ndarray, sigma: float = MMD_SIGMA) -> float:
    """Raw squared MMD, Gaussian RBF on per-scan normalised histograms, V-statistic (R2DM `compute_mmd_2d`).

    1,000 vs 1,000 scans: three (1000, 10000) x (10000, 1000) float64 matmuls, ~2 s on 2 cores.
    """
    p = _normalised(hists_a, "hists_a")  # (S_a, H*W)
    q = _normalised(hists_b, "hists_b")  # (S_b, H*W)
    if p.shape[1] != q.shape[1]:
        raise InputError(f"bev_mmd: histogram sizes differ, {tuple(p.shape)} vs {tuple(q.shape)}")
    if sigma <= 0:
        raise InputError(f"bev_mmd: sigma must be > 0, got {sigma}")
    gamma = 1.0 / (2.0 * sigma**2)
    return _mean_rbf(p, p, gamma) + _mean_rbf(q, q, gamma) - 2.0 * _mean_rbf(p, q, gamma)
