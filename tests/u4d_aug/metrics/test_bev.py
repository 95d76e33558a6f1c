"""BEV histogram, JSD and MMD (R2DM protocol) on hand-made points, random histograms and a real scan."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from u4d_aug.errors import InputError
from u4d_aug.metrics.bev import (
    MMD_REPORT_SCALE,
    bev_histogram,
    bev_histograms,
    bev_jsd,
    bev_mmd,
)


def _r2dm_histogram(points: np.ndarray) -> np.ndarray:
    """R2DM `point_cloud_to_histogram` after its 0.5-63 m evaluation mask, with torch.histogramdd."""
    xyz = torch.from_numpy(points[:, :3].astype(np.float32))
    depth = xyz.norm(dim=1)
    xyz = xyz[(depth >= 0.5) & (depth <= 63.0)]
    depth = xyz.norm(dim=1)
    xy = xyz[(depth > 3.0) & (depth < 70.0), :2]
    return torch.histogramdd(xy, bins=100, range=[-80.0, 80.0, -80.0, 80.0]).hist.numpy()


def _r2dm_mmd(h1: np.ndarray, h2: np.ndarray, sigma: float = 0.5) -> float:
    """R2DM `compute_mmd_2d` (torch.cdist + RBF, V-statistic), in float64."""
    p = torch.from_numpy(h1.reshape(len(h1), -1).astype(np.float64))
    q = torch.from_numpy(h2.reshape(len(h2), -1).astype(np.float64))
    p, q = p / p.sum(1, keepdim=True), q / q.sum(1, keepdim=True)

    def rbf(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.exp(-(torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist") ** 2) / (2 * sigma**2))

    return float(rbf(p, p).mean() + rbf(q, q).mean() - 2 * rbf(p, q).mean())


def _random_scans(rng: np.random.Generator, count: int, shift: float = 0.0) -> list[np.ndarray]:
    scans = []
    for _ in range(count):
        radius = rng.uniform(2.0, 70.0, 3000)
        angle = rng.uniform(-np.pi, np.pi, 3000)
        xyz = np.stack([radius * np.cos(angle) + shift, radius * np.sin(angle), rng.normal(-1.5, 0.3, 3000)], 1)
        scans.append(np.concatenate([xyz, rng.uniform(0, 1, (3000, 1))], 1).astype(np.float32))
    return scans


def test_histogram_hand_made_points() -> None:
    points = np.array(
        [
            [10.0, 0.0, 0.0, 0.5],  # cell (56, 50)
            [-10.0, -10.0, 1.0, 0.5],  # cell (43, 43)
            [2.0, 0.0, 0.0, 0.5],  # 2 m: below 3 m, dropped
            [0.3, 0.0, 0.0, 0.5],  # inside 0.5 m: dropped by the evaluation window
            [65.0, 0.0, 0.0, 0.5],  # beyond 63 m: dropped
            [62.0, 0.0, 0.0, 0.5],  # cell (88, 50)
        ],
        dtype=np.float32,
    )
    hist = bev_histogram(points)
    assert hist.shape == (100, 100) and hist.dtype == np.float32
    assert hist.sum() == 3
    assert hist[56, 50] == 1 and hist[43, 43] == 1 and hist[88, 50] == 1


def test_histogram_matches_r2dm_histogramdd(rng: np.random.Generator) -> None:
    points = _random_scans(rng, 1)[0]
    points[:10, :2] = rng.choice([-40.0, -20.0, 0.0, 20.0, 40.0], (10, 2))  # cell edges exact in binary
    np.testing.assert_array_equal(bev_histogram(points), _r2dm_histogram(points))


def test_histogram_real_scan(kitti_root: Path) -> None:
    from u4d_aug.data.formats import read_kitti_scan

    points = read_kitti_scan(kitti_root / "sequences" / "00" / "velodyne" / "000000.bin")
    hist = bev_histogram(points)
    depth = np.linalg.norm(points[:, :3].astype(np.float64), axis=1)
    assert hist.sum() == np.count_nonzero((depth > 3.0) & (depth <= 63.0))
    np.testing.assert_array_equal(hist, _r2dm_histogram(points))


def test_jsd_zero_symmetric_bounded(rng: np.random.Generator) -> None:
    a = bev_histograms(_random_scans(rng, 4))
    b = bev_histograms(_random_scans(rng, 3, shift=8.0))
    assert bev_jsd(a, a) == pytest.approx(0.0, abs=1e-7)
    assert bev_jsd(a, b) == pytest.approx(bev_jsd(b, a), rel=1e-12)
    assert 0.0 < bev_jsd(a, b) <= np.sqrt(np.log(2))
    left, right = np.zeros((100, 100)), np.zeros((100, 100))
    left[:50] = 1.0
    right[50:] = 1.0
    assert bev_jsd(left, right) == pytest.approx(np.sqrt(np.log(2)))  # disjoint supports: the maximum


def test_mmd_zero_grows_with_shift_and_matches_r2dm(rng: np.random.Generator) -> None:
    base = bev_histograms(_random_scans(rng, 6))
    other = bev_histograms(_random_scans(rng, 6))
    assert bev_mmd(base, base) == pytest.approx(0.0, abs=1e-12)
    values = [bev_mmd(base, bev_histograms(_random_scans(rng, 6, shift=s))) for s in (0.0, 5.0, 20.0)]
    assert values[0] < values[1] < values[2]
    assert bev_mmd(base, other) == pytest.approx(bev_mmd(other, base), rel=1e-9)
    assert bev_mmd(base, other) == pytest.approx(_r2dm_mmd(base, other), rel=1e-6, abs=1e-15)
    assert MMD_REPORT_SCALE == 1e4


def test_bad_inputs_raise_input_error() -> None:
    with pytest.raises(InputError, match="N, >=3"):
        bev_histogram(np.zeros((5, 2)))
    empty = np.zeros((2, 100, 100))
    full = np.ones((2, 100, 100))
    with pytest.raises(InputError, match="scan 0 has no points"):
        bev_mmd(empty, full)
    with pytest.raises(InputError, match="no points"):
        bev_jsd(empty, full)
    with pytest.raises(InputError, match="sizes differ"):
        bev_jsd(np.ones((10, 10)), full)
    with pytest.raises(InputError, match="no scans"):
        bev_histograms([])
