"""The structure a segmentor reads in a scan: above-ground points per occupied BEV cell, range-image roughness.

A real wall is a line in bird's-eye view: every beam that hits it lands in the same few 0.25 m cells, so those cells
hold many points. A generated wall whose depths scatter along the rays spreads the same points thinly over many
cells (radial "stars" in BEV), and a segmentor sees no wall there. "Above ground" is a point more than `margin`
above the local ground, the low `quantile` of the heights in its 2 m cell, taken as the lowest such value over the
3 x 3 cells around it (a wall's own cell may hold no ground return: it hides the ground behind it). Points count
inside the 0.5-63 m evaluation window of the BEV metrics (`bev.EVAL_MIN_DEPTH`, `bev.EVAL_MAX_DEPTH`).
Roughness is `range_view.image_roughness` along a ring and down a column.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from u4d_aug.errors import InputError
from u4d_aug.metrics.bev import EVAL_MAX_DEPTH, EVAL_MIN_DEPTH
from u4d_aug.range_view import image_roughness

BEV_CELL = 0.25  # m, the BEV cell whose above-ground points are counted
GROUND_CELL = 2.0  # m, the cells whose low heights estimate the ground
GROUND_QUANTILE = 0.1  # the ground of a cell: this quantile of its heights (a few stray returns below do not count)
ABOVE_GROUND = 0.5  # m above the local ground: above curbs and the noise of generated ground
_OFFSET = 1 << 20  # cell indices shifted non-negative before packing (x, y) into one int64 key


def _cell_keys(xy: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int64 key of the (x, y) cell of each point (N, 2): (i + 2^20) * 2^21 + (j + 2^20)."""
    ij = np.floor(xy / cell).astype(np.int64) + _OFFSET  # (N, 2)
    return ij[:, 0] * (2 * _OFFSET) + ij[:, 1]


def _in_window(points: np.ndarray) -> np.ndarray:
    """(M, >=3) points inside the 0.5-63 m evaluation window of the BEV metrics."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(f"structure metrics: expected points of shape (N, >=3), got {points.shape}")
    depth2 = np.einsum("ij,ij->i", points[:, :3].astype(np.float64), points[:, :3].astype(np.float64))
    return points[(depth2 >= EVAL_MIN_DEPTH**2) & (depth2 <= EVAL_MAX_DEPTH**2)]


def ground_height(points: np.ndarray, cell: float = GROUND_CELL, quantile: float = GROUND_QUANTILE) -> np.ndarray:
    """(N,) float64 local ground height of each point (N, >=3): min over the 3 x 3 cells around it of each cell's
    `quantile` height."""
    points = np.asarray(points)
    if len(points) == 0:
        return np.zeros(0)
    if not 0.0 <= quantile <= 1.0 or cell <= 0:
        raise InputError(f"ground_height: need cell > 0 and quantile in [0, 1], got {cell}, {quantile}")
    z = points[:, 2].astype(np.float64)  # (N,)
    keys, inverse = np.unique(_cell_keys(points[:, :2].astype(np.float64), cell), return_inverse=True)  # (C,), (N,)
    order = np.lexsort((z, inverse))  # by cell, then height
    counts = np.bincount(inverse, minlength=len(keys))  # (C,)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    low = z[order][starts + np.floor(quantile * (counts - 1)).astype(np.int64)]  # (C,) per-cell low height
    ground = np.full(len(keys), np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            neighbour = keys + di * (2 * _OFFSET) + dj  # (C,)
            at = np.minimum(np.searchsorted(keys, neighbour), len(keys) - 1)
            ground = np.minimum(ground, np.where(keys[at] == neighbour, low[at], np.inf))
    return ground[inverse]


def above_ground(points: np.ndarray, margin: float = ABOVE_GROUND, cell: float = GROUND_CELL) -> np.ndarray:
    """(N,) bool: the point (N, >=3) is more than `margin` above its local ground (`ground_height`)."""
    points = np.asarray(points)
    return points[:, 2].astype(np.float64) - ground_height(points, cell) > margin


def bev_cell_counts(points: np.ndarray, cell: float = BEV_CELL, margin: float = ABOVE_GROUND) -> np.ndarray:
    """(C,) int64 above-ground points in each occupied `cell` x `cell` BEV cell of one scan (N, >=3), inside the
    0.5-63 m evaluation window (the ground estimated from the window's points)."""
    if cell <= 0:
        raise InputError(f"bev_cell_counts: cell must be > 0, got {cell}")
    points = _in_window(points)
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    high = points[above_ground(points, margin)]  # (M, >=3)
    _, counts = np.unique(_cell_keys(high[:, :2].astype(np.float64), cell), return_counts=True)
    return counts.astype(np.int64)


def points_per_cell(scans: Iterable[np.ndarray], cell: float = BEV_CELL, margin: float = ABOVE_GROUND) -> float:
    """Above-ground points per occupied BEV cell pooled over scans: sum of the points / number of occupied cells
    (NaN when no scan has an above-ground point)."""
    points = cells = 0
    for scan in scans:
        counts = bev_cell_counts(scan, cell, margin)
        points, cells = points + int(counts.sum()), cells + len(counts)
    return points / cells if cells else float("nan")


def depth_roughness(images: torch.Tensor) -> dict[str, float]:
    """{"ring", "vertical"}: mean |encoded depth step| between adjacent returns of range images (..., 2, H, W)
    along a ring and down a column (`range_view.image_roughness`), pooled over the images."""
    return {direction: image_roughness(images, direction)[0] for direction in ("ring", "vertical")}
