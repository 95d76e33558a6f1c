"""Structure metrics on hand-made scenes (a wall over flat ground, the wall smeared along its rays) and a real scan:
above-ground points per occupied BEV cell, the local ground, the roughness pair."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.data.sensors import hdl64
from u4d_aug.errors import InputError
from u4d_aug.metrics.structure import (
    above_ground,
    bev_cell_counts,
    depth_roughness,
    ground_height,
    points_per_cell,
)
from u4d_aug.range_view import image_roughness, project, to_image


def _ground(z: float = -1.7, extent: float = 20.0, spacing: float = 0.5) -> np.ndarray:
    """Flat ground points (M, 4) on a grid over [-extent, extent]^2 at height z."""
    axis = np.arange(-extent, extent + 1e-9, spacing)
    x, y = np.meshgrid(axis, axis)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z), np.full(x.size, 0.5)], 1)


def _wall(rng: np.random.Generator, smear: float = 0.0) -> np.ndarray:
    """A wall x = 10 m, |y| <= 5 m, 0.3-3 m above the ground (z -1.4..1.3), 2000 points; `smear`: each point moved
    along its ray by N(0, smear) metres (the generated "star")."""
    y, z = rng.uniform(-5, 5, 2000), rng.uniform(-1.4, 1.3, 2000)
    xyz = np.stack([np.full(2000, 10.0), y, z], 1)
    xyz *= 1.0 + rng.normal(0.0, smear, (2000, 1)) / np.linalg.norm(xyz, axis=1, keepdims=True)
    return np.concatenate([xyz, np.full((2000, 1), 0.5)], 1)


def test_stacked_points_in_one_cell_count_and_ground_does_not() -> None:
    column = np.array([[10.1, 0.1, z, 0.5] for z in (-1.0, 0.0, 0.5, 1.0, 2.0)])  # 0.7-3.7 m above the ground
    scan = np.concatenate([_ground(), column])
    assert bev_cell_counts(scan).tolist() == [5]  # one occupied cell; the ground points are not above ground
    assert points_per_cell([scan, scan]) == pytest.approx(5.0)  # pooled: 10 points in 2 cells
    assert not above_ground(_ground()).any()


def test_a_smeared_wall_spreads_its_points_thinner() -> None:
    rng = np.random.default_rng(0)
    line = points_per_cell([np.concatenate([_ground(), _wall(rng)])])
    smeared = [points_per_cell([np.concatenate([_ground(), _wall(rng, s)])]) for s in (0.5, 2.0)]
    assert line > 5 * smeared[1] and line > smeared[0] > smeared[1]
    # 10 m / 0.25 m = 40 cells; the points more than 0.5 m above the ground (z > -1.2 of -1.4..1.3): 2000 * 2.5 / 2.7
    assert line == pytest.approx(2000 * 2.5 / 2.7 / 40, rel=0.03)


def test_local_ground_ignores_stray_low_returns_and_reaches_over_a_wall() -> None:
    ground = _ground()
    stray = np.array([[0.2, 0.2, -5.0, 0.5]])  # one return 3.3 m below the ground among ~16 in its 2 m cell
    wall_only = np.array([[22.5, 22.5, z, 0.5] for z in (0.0, 1.0)])  # the 2 m cell next to the ground grid's last
    scan = np.concatenate([ground, stray, wall_only])
    height = ground_height(scan)
    assert height[: len(ground)] == pytest.approx(-1.7)
    lonely = np.array([[45.0, 45.0, 0.0, 0.5], [45.1, 45.1, 1.0, 0.5]])  # no cell nearby: its own low height
    assert ground_height(lonely).tolist() == [0.0, 0.0]
    # a cell holding only wall points takes the ground of a neighbouring cell
    assert height[-2:] == pytest.approx(-1.7)
    with pytest.raises(InputError, match="quantile"):
        ground_height(scan, quantile=1.5)


def test_the_evaluation_window_and_empty_scans() -> None:
    far = np.array([[70.0, 0.0, z, 0.5] for z in (0.0, 1.0, 2.0)])  # beyond 63 m
    assert bev_cell_counts(far).size == 0
    assert np.isnan(points_per_cell([far, np.zeros((0, 4))]))
    with pytest.raises(InputError, match="shape"):
        bev_cell_counts(np.zeros((3, 2)))


def test_roughness_pair_is_image_roughness_both_ways() -> None:
    images = torch.rand(2, 2, 4, 6) * 2 - 1
    pair = depth_roughness(images)
    assert pair == {"ring": image_roughness(images)[0], "vertical": image_roughness(images, "vertical")[0]}


@pytest.mark.real
def test_a_real_scan_stacks_more_points_than_its_rays_smeared(kitti_root: Path) -> None:
    """Raw > projected to 64x1024 (at most one point per pixel) > projected and jittered 1 m along the rays."""
    points = read_kitti_scan(kitti_root / "sequences" / "00" / "velodyne" / "000000.bin")
    sensor = hdl64()
    projection = project(points, sensor, 64, 1024)
    shown = points[projection.winner[projection.mask].numpy()]  # (M, 4) the points the image keeps
    xyz = shown[:, :3]
    jitter = np.random.default_rng(0).normal(0.0, 1.0, (len(shown), 1)) / np.linalg.norm(xyz, axis=1, keepdims=True)
    smeared = np.concatenate([xyz * (1 + jitter), shown[:, 3:]], 1)
    raw, kept, smear = (points_per_cell([p]) for p in (points, shown, smeared))
    assert raw > kept > 1.5 * smear > 1.0, (raw, kept, smear)
    rough = depth_roughness(to_image(projection, sensor))
    assert 0 < rough["ring"] < rough["vertical"]  # neighbouring beams are further apart than neighbouring azimuths
