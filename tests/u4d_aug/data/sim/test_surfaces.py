"""Measured surface model (u4d_aug/data/sim/surfaces.py): per-material remission gain, speckle and penetration
against the materials; and the realism report's per-class and edge statistics (u4d_aug/data/sim/report.py). The
scans these terms make are tested in test_raycast.py."""

from __future__ import annotations

import numpy as np
import pytest

from u4d_aug.config import load_config
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import MATERIALS
from u4d_aug.data.sim.report import (
    INTENSITY_BINS,
    ROUGHNESS_BINS,
    edge_stats,
    intensity_distances,
    intensity_hist,
)
from u4d_aug.data.sim.surfaces import MEASURED, material_terms
from u4d_aug.errors import InputError

# ------------------------------------------------------------------------------------------------------------
# surface terms


def test_basic_terms_are_the_materials() -> None:
    terms = material_terms("basic")
    assert np.all(terms.gain == 1.0) and np.all(terms.speckle == 0.0)
    np.testing.assert_array_equal(terms.zero_prob, np.float32([m.zero_prob for m in MATERIALS]))
    np.testing.assert_array_equal(terms.penetration, np.float32([m.penetration for m in MATERIALS]))
    assert np.all(material_terms("basic", 0.3).speckle == np.float32(0.3))
    measured = material_terms("measured")
    names = [m.name for m in MATERIALS]
    for name, fit in MEASURED.items():
        k = names.index(name)
        assert measured.gain[k] == pytest.approx(fit.gain)
        if fit.penetration is not None:
            assert measured.penetration[k] == pytest.approx(fit.penetration)
    with pytest.raises(ValueError, match="surface model"):
        material_terms("glossy")
    with pytest.raises(InputError, match="lidar.surface_model"):
        load_config(SimConfig, None, ["lidar.surface_model=glossy"])
    with pytest.raises(InputError, match="lidar.speckle' must be >= 0"):
        load_config(SimConfig, None, ["lidar.speckle=-0.1"])


# ------------------------------------------------------------------------------------------------------------
# report: per-class remission histograms and edge statistics


def test_intensity_hist_and_distances() -> None:
    rng = np.random.default_rng(0)
    points = np.zeros((4000, 4), np.float32)
    points[:, 0] = rng.uniform(2.0, 60.0, 4000)
    points[:, 3] = np.round(rng.uniform(0.0, 0.6, 4000), 2)
    points[:500, 3] = 0.0
    semantic = np.where(np.arange(4000) < 2000, 40, 70).astype(np.uint16)  # road, vegetation
    hist = intensity_hist(points, semantic)
    assert hist.shape == (20, len(INTENSITY_BINS) - 1)
    assert hist.sum() == int((points[:, 0] <= 50.0).sum())  # only within the labelled range
    assert hist[8, 0] == int(((points[:, 3] == 0) & (points[:, 0] <= 50) & (semantic == 40)).sum())  # own 0 bin
    same = intensity_distances(hist, hist)
    assert same["per_class"] == {"road": 0.0, "vegetation": 0.0} and same["mean"] == 0.0
    brighter = points.copy()
    brighter[:, 3] = np.minimum(brighter[:, 3] + 0.2, 0.99)
    far = intensity_distances(intensity_hist(brighter, semantic), hist)
    assert 0.3 < far["mean"] < 1.0 and far["zero_share"]["road"]["real"] > 0.1


def _ring_scan(ranges: np.ndarray) -> np.ndarray:
    """One ring of returns 0.2 deg apart at the given ranges (x forward)."""
    azimuth = np.radians(0.2) * np.arange(len(ranges))
    return np.column_stack([ranges * np.cos(azimuth), ranges * np.sin(azimuth), np.zeros(len(ranges))])


def test_edge_stats_counts_steps_mixed_pixels_and_roughness() -> None:
    ranges = np.array([10.0] * 10 + [15.0] + [20.0] * 10 + [10.0] * 5 + [20.0] * 5)  # a mixed step, a clean step
    stats = edge_stats(_ring_scan(ranges), np.zeros(len(ranges), np.int64))
    assert stats["edges"] == 3  # each step once: 10 -> 15 -> 20 (mixed), 20 -> 10 and 10 -> 20 (clean)
    assert stats["mixed"] == 1
    noisy = 10.0 + np.random.default_rng(0).normal(0.0, 0.01, 3000)
    stats = edge_stats(_ring_scan(noisy), np.zeros(3000, np.int64))
    centers = (ROUGHNESS_BINS[:-1] + ROUGHNESS_BINS[1:]) / 2
    cdf = np.cumsum(stats["roughness_hist"]) / stats["roughness_hist"].sum()
    median = centers[np.searchsorted(cdf, 0.5)]
    assert median == pytest.approx(0.674 * np.sqrt(6) * 0.01, abs=0.002)  # |second difference| of N(0, 1 cm)
