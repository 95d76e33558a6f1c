"""LiDAR measurement model (u4d_aug/data/sim/raycast.py): the ray pattern, and scans of a wall in front of a clean
sensor: remission per material (surfaces.py) and per laser, range noise, dark dropout, mixed pixels."""

from __future__ import annotations

import numpy as np
import pytest

from u4d_aug.data.sensors import hdl32, hdl64
from u4d_aug.data.sim.config import LidarConfig
from u4d_aug.data.sim.geometry import MATERIALS, MeshBuilder, quad
from u4d_aug.data.sim.raycast import LidarSimulator, azimuth_neighbours, azimuth_steps, ray_pattern
from u4d_aug.data.sim.surfaces import MEASURED, material_terms

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


# ------------------------------------------------------------------------------------------------------------
# ray pattern


def test_azimuth_steps_per_sensor():
    assert azimuth_steps(hdl64(), LidarConfig()) == 2083 and azimuth_steps(hdl32(), LidarConfig()) == 1085
    assert azimuth_steps(hdl64(), LidarConfig(azimuth_steps=360)) == 360


def test_ray_pattern_is_ring_major_top_ring_first_counter_clockwise():
    cfg = LidarConfig(**CLEAN)
    pattern = ray_pattern(hdl64(), cfg, np.random.default_rng(0))
    assert pattern.directions.shape == (64 * 360, 3) and pattern.keep.all() and pattern.gain is None
    np.testing.assert_allclose(np.linalg.norm(pattern.directions, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(pattern.ring, np.repeat(np.arange(64), 360))
    elevation = np.arcsin(pattern.directions[:, 2]).reshape(64, 360)
    assert np.argmax(elevation[:, 0]) == 0 and np.argmin(elevation[:, 0]) == 63  # top ring first
    assert np.mean(np.diff(elevation[:, 0]) < 0) > 0.9  # (the table's medians cross in a few places)
    azimuth = np.arctan2(pattern.directions[:, 1], pattern.directions[:, 0]).reshape(64, 360)
    np.testing.assert_allclose(np.mod(azimuth[0], 2 * np.pi), 2 * np.pi * (np.arange(360) + 0.5) / 360, atol=1e-5)
    masked = ray_pattern(hdl64(), LidarConfig(**{**CLEAN, "ego_mask": True}), np.random.default_rng(0))
    blocked = ~masked.keep
    assert blocked.any() and masked.ring[blocked].min() > 32  # the ego car blocks only downward rays


def test_per_laser_gains_are_drawn_after_the_basic_pattern():
    basic = ray_pattern(hdl64(), LidarConfig(**CLEAN), np.random.default_rng(4))
    gained = ray_pattern(hdl64(), LidarConfig(**CLEAN, ring_gain_spread=0.1), np.random.default_rng(4))
    np.testing.assert_array_equal(gained.directions, basic.directions)  # the same rays, whatever the gains
    per_ring = gained.gain.reshape(64, 360)
    assert np.all(per_ring == per_ring[:, :1]) and np.std(np.log(per_ring[:, 0])) == pytest.approx(0.1, abs=0.03)
