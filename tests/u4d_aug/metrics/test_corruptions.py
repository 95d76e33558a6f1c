"""Corruptions of a scan on a tiny ray-cast scene (flat ground, two walls at y = +-8 m, HDL-64E rays): level 0 is the
scan itself, each kind grows with the level in the quantity it corrupts, one seed gives one scan, bad input is one
line."""

from __future__ import annotations

import numpy as np
import pytest

from u4d_aug.data.sensors import hdl64
from u4d_aug.errors import InputError
from u4d_aug.metrics.corruptions import (
    CORRUPTIONS,
    DEPTH_NOISE,
    MAX_DROPPED,
    corrupt,
    depth_noise,
    dropped_rows,
    ray_cells,
    smeared_walls,
    swapped_columns,
)
from u4d_aug.range_view import ray_angles

GROUND_Z, WALL_Y, WALL_TOP, EXTENT = -1.73, 8.0, 3.0, 30.0
LEVELS = (0.0, 0.25, 0.5, 1.0)


def scene(wall_y: float = WALL_Y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, 4) float32 of the HDL-64E's 64 x 1024 bin-centre rays cast on the ground z = -1.73 m (|x|, |y| <=
    30 m) and two walls y = +-`wall_y` (|x| <= 30 m, up to z = 3 m); with each point's ring and column (N,)."""
    elevation, azimuth = (a.double().numpy() for a in ray_angles(hdl64()))
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")  # (64, 1024)
    rows, cols = np.meshgrid(np.arange(64), np.arange(1024), indexing="ij")
    ray = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)  # (64, 1024, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(ray[..., 2] < 0, GROUND_Z / ray[..., 2], np.inf)
        t_wall = np.where(np.abs(ray[..., 1]) > 1e-6, wall_y / np.abs(ray[..., 1]), np.inf)
    hit_ground = t_ground[..., None] * ray
    hit_wall = t_wall[..., None] * ray
    ground_ok = (np.abs(hit_ground[..., 0]) <= EXTENT) & (np.abs(hit_ground[..., 1]) <= EXTENT)
    wall_ok = (np.abs(hit_wall[..., 0]) <= EXTENT) & (hit_wall[..., 2] <= WALL_TOP) & (hit_wall[..., 2] >= GROUND_Z)
    t = np.minimum(np.where(ground_ok, t_ground, np.inf), np.where(wall_ok, t_wall, np.inf))  # (64, 1024)
    hit = np.isfinite(t)
    xyz = t[hit][:, None] * ray[hit]  # (N, 3)
    reflectance = np.where(np.isclose(np.abs(xyz[:, 1]), wall_y), 0.6, 0.3)[:, None]
    return np.concatenate([xyz, reflectance], 1).astype(np.float32), rows[hit], cols[hit]


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    return scene()[0]


def _ranges(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points[:, :3].astype(np.float64), axis=1)


def test_rings_and_columns_are_those_of_the_rays_cast() -> None:
    points, rows, cols = scene()
    found_rows, found_cols = ray_cells(points, hdl64())
    assert np.array_equal(found_rows, rows) and np.array_equal(found_cols, cols)
    assert len(np.unique(rows)) == 64  # every ring hits the ground or a wall somewhere
    origin = ray_cells(np.zeros((1, 4), np.float32), hdl64())
    assert origin[0].tolist() == [-1] and origin[1].tolist() == [-1]


@pytest.mark.parametrize("kind", CORRUPTIONS)
def test_level_zero_is_the_scan_itself_and_every_level_keeps_float32_and_reflectance(points, kind) -> None:
    same = corrupt(points, kind, 0.0, np.random.default_rng(0))
    assert same.dtype == np.float32 and np.array_equal(same, points) and same is not points
    for level in LEVELS[1:]:
        out = corrupt(points, kind, level, np.random.default_rng(0))
        assert out.dtype == np.float32 and out.shape[1] == 4 and np.isfinite(out).all()
        if len(out) == len(points):
            assert np.array_equal(out[:, 3], points[:, 3])


def test_depth_noise_moves_points_along_their_rays_by_level_times_ten_percent(points) -> None:
    ranges = _ranges(points)
    change = []
    for level in LEVELS[1:]:
        noisy = depth_noise(points, level, np.random.default_rng(1))
        direction = noisy[:, :3] / np.linalg.norm(noisy[:, :3], axis=1, keepdims=True)
        assert np.allclose(direction, points[:, :3] / ranges[:, None], atol=1e-5)  # along the ray
        change.append(float(np.mean(np.abs(_ranges(noisy) / ranges - 1.0))))
    assert change[0] < change[1] < change[2]
    assert change[2] == pytest.approx(DEPTH_NOISE * np.sqrt(2.0 / np.pi), rel=0.03)  # E|N(0, 0.1)|


def test_smeared_walls_spread_the_walls_along_their_rays_and_leave_the_ground(points) -> None:
    wall = np.isclose(np.abs(points[:, 1]), WALL_Y) & (points[:, 2] > GROUND_Z + 0.6)  # clearly above the ground
    spread, moved = [], []
    for level in LEVELS:
        out = smeared_walls(points, level, np.random.default_rng(2))
        distance = np.abs(out[wall, 1]).astype(np.float64)  # a wall point's distance from the x axis, 8 m if in place
        spread.append(float(np.std(distance)))
        moved.append(float(np.mean(np.abs(distance - WALL_Y) > 1e-3)))
        assert np.array_equal(out[points[:, 2] < GROUND_Z + 0.01], points[points[:, 2] < GROUND_Z + 0.01])
    assert spread[0] < 1e-5 < spread[1] < spread[2] < spread[3]
    assert moved == pytest.approx(list(LEVELS), abs=0.06)  # a share `level` of the azimuth blocks


def test_dropped_rows_remove_whole_rings(points) -> None:
    left = []
    for level in LEVELS:
        out = dropped_rows(points, level, np.random.default_rng(3))
        left.append(len(np.unique(ray_cells(out, hdl64())[0])))
    assert left == [64 - round(level * MAX_DROPPED * 64) for level in LEVELS] == [64, 52, 40, 16]


def test_swapped_columns_move_a_share_level_of_the_points_about_z(points) -> None:
    for level in LEVELS:
        out = swapped_columns(points, level, np.random.default_rng(4))
        moved = float(np.mean(np.abs(out[:, :2] - points[:, :2]).max(1) > 1e-4))
        assert moved == pytest.approx(level, abs=0.03)
        assert np.allclose(_ranges(out), _ranges(points), rtol=1e-5) and np.array_equal(out[:, 2], points[:, 2])
    _, cols = ray_cells(points, hdl64())
    _, new_cols = ray_cells(swapped_columns(points, 1.0, np.random.default_rng(4)), hdl64())
    per_column = np.bincount(cols, minlength=1024)
    assert sorted(np.bincount(new_cols, minlength=1024)) == sorted(per_column)  # whole columns trade places


@pytest.mark.parametrize("kind", CORRUPTIONS)
def test_one_seed_gives_one_scan(points, kind) -> None:
    first = corrupt(points, kind, 0.5, np.random.default_rng(7))
    again = corrupt(points, kind, 0.5, np.random.default_rng(7))
    other = corrupt(points, kind, 0.5, np.random.default_rng(8))
    assert np.array_equal(first, again)
    assert first.shape != other.shape or not np.array_equal(first, other)


def test_bad_kind_level_or_shape_is_one_line(points) -> None:
    with pytest.raises(InputError, match="'stars' is not one of depth_noise, smeared_walls, dropped_rows, swapped_co"):
        corrupt(points, "stars", 0.5, np.random.default_rng(0))
    for level in (-0.1, 1.5):
        with pytest.raises(InputError, match=r"level must be in \[0, 1\]"):
            corrupt(points, "dropped_rows", level, np.random.default_rng(0))
    with pytest.raises(InputError, match=r"shape \(N, 4\)"):
        corrupt(points[:, :3], "depth_noise", 0.5, np.random.default_rng(0))
