"""Range view: depth encoding, ray angles, nearest-wins projection, index maps, batching, real round trip."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from u4d_aug.data.sensors import Sensor, hdl32, hdl64
from u4d_aug.errors import InputError
from u4d_aug.range_view import (
    decode_depth,
    encode_depth,
    image_roughness,
    project,
    project_batch,
    ray_angles,
    roundtrip_stats,
    scatter_to_image,
    to_image,
    unproject,
)

TINY = Sensor("tiny", (10.0, 0.0, -10.0, -20.0), 1.0, 50.0, 4, 16, 15.0, -25.0)


def _kitti_scan(kitti_root: Path, frame: int = 0) -> torch.Tensor:
    path = kitti_root / "sequences" / "00" / "velodyne" / f"{frame:06d}.bin"
    return torch.from_numpy(np.fromfile(path, dtype=np.float32).reshape(-1, 4))


def _points_on_rays(elevation: torch.Tensor, azimuth: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """(N, 4) points at the given angles (radians) and depths, intensity 0.5."""
    x = depth * torch.cos(elevation) * torch.cos(azimuth)
    y = depth * torch.cos(elevation) * torch.sin(azimuth)
    z = depth * torch.sin(elevation)
    return torch.stack([x, y, z, torch.full_like(x, 0.5)], dim=1)


def _random_scan(generator: torch.Generator, num_points: int) -> torch.Tensor:
    elevation = torch.deg2rad(torch.rand(num_points, generator=generator) * 40.0 - 28.0)
    azimuth = (torch.rand(num_points, generator=generator) * 2 - 1) * math.pi
    depth = torch.rand(num_points, generator=generator) * 90.0
    points = _points_on_rays(elevation, azimuth, depth)
    points[:, 3] = torch.rand(num_points, generator=generator)
    return points


# --- depth encoding --------------------------------------------------------------------------------------


def test_encode_depth_golden_values() -> None:
    depth = torch.tensor([0.0, 8.0, 80.0, 200.0])
    # log2(8 + 1) / log2(80 + 1) = 1/2 exactly -> 0 in [-1, 1]
    torch.testing.assert_close(encode_depth(depth, 80.0), torch.tensor([-1.0, 0.0, 1.0, 1.0]))
    torch.testing.assert_close(decode_depth(torch.tensor([-1.0, 0.0, 1.0]), 80.0), torch.tensor([0.0, 8.0, 80.0]))


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(0.0, 80.0, allow_nan=False), min_size=1, max_size=20),
    st.sampled_from([50.0, 80.0, 100.0]),
)
def test_depth_round_trip(depths: list[float], max_depth: float) -> None:
    depth = torch.tensor(depths, dtype=torch.float64).clamp(max=max_depth)
    decoded = decode_depth(encode_depth(depth, max_depth), max_depth)
    torch.testing.assert_close(decoded, depth, rtol=1e-9, atol=1e-9)


# --- ray angles ------------------------------------------------------------------------------------------


def test_ray_angles_bin_centres() -> None:
    elevation, azimuth = ray_angles(hdl64(), 64, 1024, "linear")
    assert elevation.shape == (64,) and azimuth.shape == (1024,)
    assert math.degrees(elevation[0]) == pytest.approx(3.0 - 28.0 / 128, abs=1e-5)
    assert math.degrees(elevation[-1]) == pytest.approx(-25.0 + 28.0 / 128, abs=1e-5)
    assert float(azimuth[0]) == pytest.approx(math.pi - math.pi / 1024, abs=1e-6)
    assert float(azimuth[512]) == pytest.approx(-math.pi / 1024, abs=1e-6)
    beam, _ = ray_angles(hdl64(), row_mode="beam")
    torch.testing.assert_close(beam, torch.deg2rad(torch.tensor(hdl64().elevations_deg)))


@pytest.mark.parametrize(("sensor", "row_mode"), [(TINY, "beam"), (TINY, "linear"), (hdl32(), "beam")])
def test_point_on_each_ray_lands_in_its_own_pixel(sensor: Sensor, row_mode: str) -> None:
    height, width = sensor.height, sensor.width
    elevation, azimuth = ray_angles(sensor, height, width, row_mode)
    el = elevation[:, None].expand(height, width).reshape(-1)
    az = azimuth[None, :].expand(height, width).reshape(-1)
    points = _points_on_rays(el.double(), az.double(), torch.full_like(el, 10.0).double()).float()
    projection = project(points, sensor, height, width, row_mode)
    torch.testing.assert_close(projection.pixel, torch.arange(height * width))
    assert bool(projection.mask.all())


# --- projection ------------------------------------------------------------------------------------------


def test_nearest_point_wins_a_collision() -> None:
    direction = torch.tensor([1.0, 0.2, 0.05])
    direction = direction / direction.norm()
    points = torch.zeros(5, 4)
    points[:, :3] = direction * torch.tensor([10.0, 4.0, 7.0, 4.0, 0.5])[:, None]  # 4 m twice; 0.5 m < min_range
    points[:, 3] = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5])
    projection = project(points, TINY)
    assert len(set(projection.pixel[:4].tolist())) == 1 and projection.pixel[4] == -1
    row, col = divmod(int(projection.pixel[0]), TINY.width)
    assert int(projection.winner[row, col]) == 1  # nearest; the tie at 4 m goes to the lower index
    assert float(projection.depth[row, col]) == pytest.approx(4.0)
    assert float(projection.reflectance[row, col]) == pytest.approx(0.2)
    assert int(projection.mask.sum()) == 1 and int((projection.winner >= 0).sum()) == 1


def test_out_of_range_and_non_finite_points_are_not_projected() -> None:
    points = torch.tensor(
        [
            [0.5, 0.0, 0.0, 1.0],  # too close
            [60.0, 0.0, 0.0, 1.0],  # too far
            [0.0, 0.0, 0.0, 1.0],  # origin: no direction
            [math.nan, 1.0, 0.0, 1.0],
            [math.inf, 1.0, 0.0, 1.0],
            [5.0, 0.0, 0.0, 1.0],  # kept
        ]
    )
    projection = project(points, TINY)
    assert projection.pixel[:5].tolist() == [-1] * 5 and projection.pixel[5] >= 0
    assert int(projection.mask.sum()) == 1
    image = to_image(projection, TINY)
    assert image.shape == (2, 4, 16)
    assert bool((image[:, ~projection.mask] == -1).all())  # no return = -1 in both channels


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 400), st.sampled_from(["beam", "linear"]))
def test_pixel_and_winner_are_consistent(seed: int, num_points: int, row_mode: str) -> None:
    points = _random_scan(torch.Generator().manual_seed(seed), num_points)
    projection = project(points, TINY, row_mode=row_mode)
    depth = points[:, :3].norm(dim=1)
    in_range = (depth >= TINY.min_range) & (depth <= TINY.max_range)
    assert torch.equal(projection.pixel >= 0, in_range)
    winner = projection.winner.reshape(-1)
    shown = winner >= 0
    assert torch.equal(shown, projection.mask.reshape(-1))
    # every winner sits in its own pixel, every pixel hit by a point has a winner no farther than that point
    assert torch.equal(projection.pixel[winner[shown]], torch.nonzero(shown).squeeze(1))
    hit = projection.pixel[in_range]
    assert bool(shown[hit].all())
    assert bool((projection.depth.reshape(-1)[hit] <= depth[in_range] + 1e-5).all())
    torch.testing.assert_close(projection.depth.reshape(-1)[shown], depth[winner[shown]])


def test_rows_match_reference_formulas(kitti_root: Path) -> None:
    points = _kitti_scan(kitti_root).double()
    sensor = hdl64()
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    depth = points[:, :3].norm(dim=1)
    elevation = torch.atan2(z, torch.hypot(x, y))
    keep = (depth >= sensor.min_range) & (depth <= sensor.max_range)
    rings = torch.deg2rad(torch.tensor(sensor.elevations_deg, dtype=torch.float64))
    beam_rows = (elevation[:, None] - rings[None, :]).abs().argmin(dim=1)  # nearest ring
    fov_up, fov_down = math.radians(3.0), math.radians(-25.0)
    linear_rows = torch.floor((1 - (elevation - fov_down) / (fov_up - fov_down)) * 64).clamp(0, 63).long()
    for row_mode, reference in [("beam", beam_rows), ("linear", linear_rows)]:
        rows = project(points.float(), sensor, 64, 1024, row_mode).pixel[keep] // 1024
        mismatch = (rows != reference[keep]).float().mean()
        assert float(mismatch) < 1e-4, row_mode  # only float32-vs-float64 rounding at bin edges


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.floats(-60.0, 60.0), min_size=2, max_size=40, unique=True),
    st.integers(0, 2**31 - 1),
)
def test_beam_rows_are_nearest_ring_for_any_table(elevations: list[float], seed: int) -> None:
    table = sorted(elevations, reverse=True)
    # rings closer than 0.05 deg are not a sensor: float32 angles cannot separate them reliably
    assume(min(a - b for a, b in zip(table[:-1], table[1:])) >= 0.05)
    sensor = Sensor("random", tuple(table), 1.0, 100.0, len(table), 32, 70.0, -70.0)
    generator = torch.Generator().manual_seed(seed)
    elevation = torch.deg2rad(torch.rand(500, generator=generator, dtype=torch.float64) * 150.0 - 75.0)
    azimuth = (torch.rand(500, generator=generator, dtype=torch.float64) * 2 - 1) * math.pi
    points = _points_on_rays(elevation, azimuth, torch.full_like(elevation, 10.0)).float()
    rows = project(points, sensor).pixel // sensor.width
    xyz = points[:, :3].double()
    measured = torch.atan2(xyz[:, 2], xyz[:, :2].norm(dim=1))
    distance = (measured[:, None] - torch.deg2rad(torch.tensor(table, dtype=torch.float64))[None, :]).abs()
    nearest = distance.argmin(dim=1)
    # equal unless the point sits within float32 rounding of the midpoint between two rings
    chosen = distance.gather(1, rows[:, None]).squeeze(1)
    assert bool(((rows == nearest) | (chosen - distance.min(dim=1).values < 1e-6)).all())


def test_columns_follow_r2dm_azimuth_convention() -> None:
    azimuth = torch.tensor([0.1, 1.7, -1.4, math.pi - 1e-3, -math.pi + 1e-3])  # away from column edges
    points = _points_on_rays(torch.zeros(5), azimuth, torch.full((5,), 10.0))
    width = 8
    projection = project(points, TINY, width=width, row_mode="linear")
    expected = [math.floor(((-a / math.pi + 1) / 2 % 1) * width) for a in azimuth.tolist()]
    assert (projection.pixel % width).tolist() == expected == [3, 1, 5, 0, 7]


def test_scatter_to_image_labels_and_probabilities() -> None:
    points = _random_scan(torch.Generator().manual_seed(1), 300)
    labels = torch.arange(300) % 7
    projection = project(points, TINY)
    image = scatter_to_image(labels, projection, fill=-1)
    assert image.shape == (4, 16) and image.dtype == labels.dtype
    assert torch.equal(image[projection.mask], labels[projection.winner[projection.mask]])
    assert bool((image[~projection.mask] == -1).all())
    probabilities = torch.softmax(torch.randn(300, 5, generator=torch.Generator().manual_seed(2)), dim=1)
    prob_image = scatter_to_image(probabilities, projection)
    assert prob_image.shape == (4, 16, 5)
    torch.testing.assert_close(prob_image[projection.mask], probabilities[projection.winner[projection.mask]])
    with pytest.raises(InputError, match="rows"):
        scatter_to_image(labels[:10], projection)


@pytest.mark.parametrize("row_mode", ["beam", "linear"])
def test_batch_equals_per_scan(row_mode: str) -> None:
    generator = torch.Generator().manual_seed(3)
    scans = [_random_scan(generator, n) for n in (50, 0, 400, 123)]
    batched = project_batch(scans, TINY, row_mode=row_mode)
    assert batched.depth.shape == (4, 4, 16)
    assert batched.offsets.tolist() == [0, 50, 50, 450, 573]
    images = to_image(batched, TINY)
    assert images.shape == (4, 2, 4, 16)
    for b, scan in enumerate(scans):
        single = project(scan, TINY, row_mode=row_mode)
        start = int(batched.offsets[b])
        assert torch.equal(batched.depth[b], single.depth) and torch.equal(batched.mask[b], single.mask)
        assert torch.equal(batched.reflectance[b], single.reflectance)
        shifted = torch.where(single.winner >= 0, single.winner + start, single.winner)
        assert torch.equal(batched.winner[b], shifted)
        pixel = batched.pixel[start : start + len(scan)]
        assert torch.equal(pixel, torch.where(single.pixel >= 0, single.pixel + b * 64, single.pixel))
        assert torch.equal(images[b], to_image(single, TINY))


def test_unproject_shapes_mask_and_batch() -> None:
    scans = [_random_scan(torch.Generator().manual_seed(s), 200) for s in (4, 5)]
    batched = project_batch(scans, TINY)
    images = to_image(batched, TINY)
    points, valid = unproject(images, TINY, "beam")
    assert points.shape == (2, 4, 16, 4) and valid.shape == (2, 4, 16)
    assert torch.equal(valid, batched.mask)
    assert bool((points[~valid] == 0).all())
    torch.testing.assert_close(points[valid][:, :3].norm(dim=1), batched.depth[valid], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(points[valid][:, 3], batched.reflectance[valid], rtol=0, atol=1e-6)
    _, masked = unproject(images, TINY, "beam", mask=torch.zeros(4, 16, dtype=torch.bool))
    assert not bool(masked.any())


def test_bad_arguments() -> None:
    points = torch.ones(3, 4)
    with pytest.raises(InputError, match="row_mode 'rings' is not one of beam, linear"):
        project(points, TINY, row_mode="rings")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="needs height == number of rings"):
        project(points, hdl64(), 32, 1024, "beam")
    with pytest.raises(InputError, match=r"shape \(N, 4\)"):
        project(torch.ones(3, 3), TINY)
    with pytest.raises(InputError, match="at least one scan"):
        project_batch([], TINY)
    with pytest.raises(InputError, match=r"\(\.\.\., 2, H, W\)"):
        unproject(torch.zeros(3, 4, 16), TINY)


def test_numpy_input_and_float64_accepted() -> None:
    points = _random_scan(torch.Generator().manual_seed(6), 100)
    from_numpy = project(points.double().numpy(), TINY)
    assert torch.equal(from_numpy.pixel, project(points, TINY).pixel)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available on this machine")
def test_cuda_matches_cpu() -> None:
    scans = [_random_scan(torch.Generator().manual_seed(s), 500) for s in (7, 8)]
    cpu = project_batch(scans, TINY)
    gpu = project_batch([s.cuda() for s in scans], TINY)
    assert torch.equal(gpu.winner.cpu(), cpu.winner) and torch.equal(gpu.pixel.cpu(), cpu.pixel)
    points, valid = unproject(to_image(gpu, TINY), TINY)
    assert points.is_cuda and torch.equal(valid.cpu(), cpu.mask)


# --- real scan -------------------------------------------------------------------------------------------


def test_real_frame0_round_trip_64x2048_beam(kitti_root: Path) -> None:
    stats = roundtrip_stats(_kitti_scan(kitti_root), hdl64(), 64, 2048, "beam")
    assert stats["points"] == 124668
    assert stats["kept_fraction"] >= 0.85
    assert stats["median_error_m"] <= 0.03
    assert stats["p99_error_m"] < 0.5


def test_real_frame0_labels_project(kitti_root: Path) -> None:
    points = _kitti_scan(kitti_root)
    raw = np.fromfile(kitti_root / "sequences" / "00" / "labels" / "000000.label", dtype=np.uint32)
    semantic = torch.from_numpy((raw & 0xFFFF).astype(np.int64))
    projection = project(points, hdl64(), 64, 2048, "beam")
    image = scatter_to_image(semantic, projection, fill=-1)
    assert bool((image[projection.mask] >= 0).all()) and bool((image[~projection.mask] == -1).all())
    road_rows = torch.nonzero(image == 40)[:, 0].float()  # raw id 40 = road: seen below the horizon
    assert float(road_rows.median()) > 32


def test_image_roughness_counts_only_steps_between_returns() -> None:
    x0 = torch.full((1, 2, 2, 4), -1.0)  # no returns
    x0[0, 0, 0] = torch.tensor([0.0, 0.5, -1.0, 0.2])  # steps 0.5 (both returns), then two steps touching a hole
    x0[0, 0, 1] = torch.tensor([0.1, 0.1, 0.4, -1.0])  # steps 0.0 and 0.3
    rough, returns = image_roughness(x0)
    assert rough == pytest.approx((0.5 + 0.0 + 0.3) / 3) and returns == pytest.approx(6 / 8)
    assert image_roughness(x0[0]) == (rough, returns)  # any leading shape
    assert math.isnan(image_roughness(torch.full((2, 3, 3), -1.0))[0])  # no returns: no steps to average


def test_vertical_roughness_steps_down_the_columns() -> None:
    x0 = torch.full((2, 3, 2), -1.0)
    x0[0, :, 0] = torch.tensor([0.0, 0.5, 0.4])  # column 0: steps 0.5 and 0.1
    x0[0, :, 1] = torch.tensor([0.2, -1.0, 0.2])  # column 1: the hole leaves no step
    rough, returns = image_roughness(x0, "vertical")
    assert rough == pytest.approx((0.5 + 0.1) / 2) and returns == pytest.approx(5 / 6)
    assert image_roughness(x0.transpose(-1, -2), "ring")[0] == pytest.approx(rough)  # ring = vertical of the transpose
    with pytest.raises(InputError, match="ring, vertical"):
        image_roughness(x0, "diagonal")
