"""Measured sensor and surface model (u4d_aug/data/sim/raycast.py, surfaces.py): intensity per material, range
noise, dark dropout, per-laser gain, mixed pixels; and the realism report's per-class and edge statistics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from u4d_aug.config import load_config
from u4d_aug.data.sensors import hdl64
from u4d_aug.data.sim.config import LidarConfig, SimConfig
from u4d_aug.data.sim.geometry import MATERIALS, MeshBuilder, quad
from u4d_aug.data.sim.raycast import LidarSimulator, azimuth_neighbours, ray_pattern
from u4d_aug.data.sim.report import (
    INTENSITY_BINS,
    ROUGHNESS_BINS,
    edge_stats,
    intensity_distances,
    intensity_hist,
)
from u4d_aug.data.sim.surfaces import MEASURED, material_terms
from u4d_aug.errors import InputError

# a clean sensor: no noise, every return keeps its exact remission (0.0001 steps), nothing is zeroed by a threshold
CLEAN = dict(
    azimuth_steps=360,
    ego_mask=False,
    range_noise=0.0,
    random_drop=0.0,
    intensity_noise=0.0,
    zero_threshold=(0.0, 0.0),
    intensity_step=0.0001,
    elevation_jitter_deg=0.0,
    azimuth_jitter_deg=0.0,
    mount_tilt_deg=0.0,
)


def _wall(distance: float, material: str, reflectivity: float, label: str = "building", y=(-200.0, 200.0)):
    """Vertical wall x = distance facing the sensor (at the origin, 1.8 m above the ground)."""
    mb = MeshBuilder()
    mb.add(
        quad((distance, y[0], -5.0), (distance, y[1], -5.0), (distance, y[1], 30.0), (distance, y[0], 30.0)),
        label,
        material,
        reflectivity,
    )
    return mb


def _scan(mb: MeshBuilder, seed: int = 0, **lidar):
    cfg = LidarConfig(**{**CLEAN, **lidar})
    pattern = ray_pattern(hdl64(), cfg, np.random.default_rng(seed))
    sim = LidarSimulator(mb.build(), hdl64(), cfg, pattern)
    return sim.scan(np.eye(4), None, np.random.default_rng(seed + 1)), cfg


def _front(scan, half_width: float = 5.0) -> np.ndarray:
    """Returns facing the sensor straight on (|y| small, |z| small: incidence near normal)."""
    x, y, z = scan.points[:, :3].T
    return (x > 0) & (np.abs(y) < half_width) & (np.abs(z) < 2.0)


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


@pytest.mark.parametrize("material", ["grass", "asphalt", "facade"])
def test_measured_remission_per_material(material: str) -> None:
    """Mean remission scales by the material's gain (speckle keeps the mean); its zero share is its zero_prob."""
    basic, _ = _scan(_wall(10.0, material, 0.4))
    measured, _ = _scan(_wall(10.0, material, 0.4), surface_model="measured")
    fit = MEASURED[material]
    terms = material_terms("measured")
    k = [m.name for m in MATERIALS].index(material)
    assert len(basic.points) == len(measured.points)  # nothing dropped: the same rays, in the same order
    front = _front(basic) & (basic.points[:, 3] > 0)  # the basic model zeroes a share of asphalt and facade too
    a, b = basic.points[front, 3], measured.points[front, 3]
    assert len(a) > 1000
    nonzero = b[b > 0]
    assert np.mean(b == 0) == pytest.approx(terms.zero_prob[k], abs=0.03)
    assert nonzero.mean() / a[a > 0].mean() == pytest.approx(fit.gain, rel=0.04)
    spread = np.std(np.log(nonzero / a[b > 0]))  # per-return log-normal speckle
    assert spread == pytest.approx(terms.speckle[k], abs=0.03)


def test_ring_gain_spread_gives_each_laser_its_gain() -> None:
    scan, _ = _scan(_wall(10.0, "facade", 0.4), ring_gain_spread=0.1)
    flat, _ = _scan(_wall(10.0, "facade", 0.4))
    front, ref = _front(scan, 20.0), _front(flat, 20.0)
    lit, lit_ref = scan.points[:, 3] > 0, flat.points[:, 3] > 0  # facade: 1 % of the returns read 0
    per_ring = [scan.points[front & lit & (scan.ring == r), 3].mean() for r in np.unique(scan.ring[front])]
    base = [flat.points[ref & lit_ref & (flat.ring == r), 3].mean() for r in np.unique(flat.ring[ref])]
    log_gain = np.log(np.array(per_ring) / np.array(base))
    assert np.std(log_gain) == pytest.approx(0.1, abs=0.04)  # 30-odd lasers see the wall
    assert np.allclose(base, base[0], rtol=0.02)  # the basic model: one gain


# ------------------------------------------------------------------------------------------------------------
# range noise, dark dropout, mixed pixels


@pytest.mark.parametrize("distance", [10.0, 40.0])
def test_range_noise_grows_with_range(distance: float) -> None:
    scan, cfg = _scan(_wall(distance, "facade", 0.4), range_noise=0.008, range_noise_per_m=0.0003)
    front = _front(scan, 0.25 * distance)
    points = scan.points[front, :3].astype(np.float64)
    direction = points / np.linalg.norm(points - [0, 0, 0], axis=1, keepdims=True)
    true_range = distance / direction[:, 0]  # the laser origins sit on the z axis: x is untouched
    error = np.linalg.norm(points, axis=1) - true_range
    expected = np.hypot(cfg.range_noise, cfg.range_noise_per_m * distance)
    assert np.std(error) == pytest.approx(expected, rel=0.15)


def test_dark_returns_are_lost() -> None:
    dark, bright = _wall(10.0, "asphalt", 0.005), _wall(10.0, "asphalt", 0.4)
    kept = {}
    for name, mb in (("dark", dark), ("bright", bright)):
        for drop in (0.0, 0.8):
            scan, _ = _scan(mb, dark_drop=drop, dark_level=0.03)
            kept[name, drop] = int(_front(scan).sum())
    lost = 0.8 * (1.0 - 0.005 / 0.03)  # signal 0.005, a sixth of dark_level
    assert kept["dark", 0.8] == pytest.approx((1.0 - lost) * kept["dark", 0.0], rel=0.1)
    assert kept["bright", 0.8] == kept["bright", 0.0]  # bright returns stay


def test_mixed_pixels_at_depth_edges() -> None:
    mb = _wall(20.0, "facade", 0.4)
    front = _wall(10.0, "facade", 0.4, y=(-200.0, 0.0))  # a nearer wall covering the right half
    for args in zip(front._vertices, front._triangles):
        mb.add((args[0], args[1] - args[1].min()), "building", "facade", 0.4)
    counts = {}
    for prob in (0.0, 1.0):
        scan, _ = _scan(mb, mixed_pixel_prob=prob, mixed_pixel_jump=0.5)
        x = scan.points[:, 0]
        counts[prob] = int(((x > 10.5) & (x < 19.5)).sum())  # returns floating between the two walls
    assert counts[0.0] == 0
    rings = 64
    assert rings * 0.5 <= counts[1.0] <= rings * 2  # about one per ring at the edge (both walls seen by ~all rings)


def test_azimuth_neighbours_wrap_and_skip_masked_rays() -> None:
    ring = np.repeat(np.arange(2), 4).astype(np.int16)  # 2 rings x 4 azimuth steps
    keep = np.array([1, 1, 0, 1, 1, 1, 1, 1], dtype=bool)
    following = azimuth_neighbours(ring, keep)  # kept rays: 0 1 3 | 4 5 6 7 -> positions 0..6
    np.testing.assert_array_equal(following, [1, -1, 0, 4, 5, 6, 3])


def test_new_terms_off_by_default() -> None:
    cfg = LidarConfig()
    assert cfg.surface_model == "basic" and cfg.mixed_pixel_prob == 0 and cfg.dark_drop == 0
    assert cfg.ring_gain_spread == 0 and cfg.speckle == 0 and cfg.range_noise_per_m == 0
    varied = load_config(SimConfig, "sim/varied", []).lidar
    assert varied.surface_model == "measured" and dataclasses.asdict(varied) != dataclasses.asdict(cfg)


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
