"""Sensor models: the HDL-64E table re-measured from the real KITTI scans, HDL-32E facts, yaml sensors."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from tests.tiny_nets import REPO
from u4d_aug.data.sensors import (
    Sensor,
    fit_intensity_response,
    get_sensor,
    hdl32,
    hdl64,
    intensity_response,
    measure_ring_elevations,
)
from u4d_aug.errors import InputError

EXAMPLE_YAML = REPO / "configs" / "sensors" / "example_sensor.yaml"
NUSCENES_DEMO = Path("nuscenes_mmdet3d_demo/samples/LIDAR_TOP") / (
    "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
)


def _kitti_scan(kitti_root: Path, frame: int) -> np.ndarray:
    path = kitti_root / "sequences" / "00" / "velodyne" / f"{frame:06d}.bin"
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


def test_hdl64_table_matches_remeasured_real_scans(kitti_root: Path) -> None:
    per_scan = np.stack([measure_ring_elevations(_kitti_scan(kitti_root, i)) for i in range(6)])  # (6, 64)
    measured = np.median(per_scan, axis=0)
    table = np.array(hdl64().elevations_deg)
    assert per_scan.shape == (6, 64)
    np.testing.assert_allclose(table, measured, atol=0.05)


def test_hdl64_layout_facts() -> None:
    sensor = hdl64()
    elevations = np.array(sensor.elevations_deg)
    spacing = -np.diff(elevations)
    assert len(elevations) == 64 == sensor.height
    assert abs(elevations[0] - 2.57) < 0.1 and abs(elevations[-1] + 23.74) < 0.05
    assert np.all(spacing > 0)
    assert abs(spacing[:31].mean() - 0.333) < 0.01  # upper block ~1/3 deg
    assert abs(spacing[32:].mean() - 0.495) < 0.01  # lower block ~1/2 deg
    assert abs(spacing[31] - 0.64) < 0.05  # gap between the blocks
    assert (sensor.min_range, sensor.max_range, sensor.width) == (1.45, 80.0, 1024)
    assert (sensor.fov_up_deg, sensor.fov_down_deg) == (3.0, -25.0)


def test_measure_ring_elevations_on_synthetic_rings() -> None:
    elevations = np.array([2.0, 0.0, -3.0])
    azimuth = np.linspace(-np.pi, np.pi, 1000, endpoint=False)
    rings = [
        np.stack([np.cos(azimuth), np.sin(azimuth), np.full_like(azimuth, np.tan(np.radians(e)))], 1)
        for e in elevations
    ]
    points = np.concatenate(rings) * 10.0
    np.testing.assert_allclose(measure_ring_elevations(points), elevations, atol=1e-9)


def test_hdl32_facts() -> None:
    sensor = hdl32()
    elevations = np.array(sensor.elevations_deg)
    assert len(elevations) == 32 == sensor.height and sensor.width == 1024
    assert elevations[0] == pytest.approx(10.67) and elevations[-1] == pytest.approx(-30.67)
    np.testing.assert_allclose(-np.diff(elevations), 41.34 / 31, atol=1e-3)
    assert (sensor.min_range, sensor.max_range) == (1.0, 100.0)
    assert (sensor.fov_up_deg, sensor.fov_down_deg) == (10.0, -30.0)


def test_hdl32_table_matches_real_nuscenes_rings(real_root: Path) -> None:
    elevations = np.array(hdl32().elevations_deg)
    raw = np.fromfile(real_root / NUSCENES_DEMO, dtype=np.float32).reshape(-1, 5)
    raw = raw[np.linalg.norm(raw[:, :3], axis=1) > 1.0]
    elevation = np.degrees(np.arctan2(raw[:, 2], np.hypot(raw[:, 0], raw[:, 1])))
    ring = raw[:, 4].astype(int)  # nuScenes ring 0 is the bottom ring
    medians = np.array([np.median(elevation[ring == r]) for r in range(32)])[::-1]
    np.testing.assert_allclose(elevations, medians, atol=0.15)


def test_get_sensor_names_and_yaml() -> None:
    assert get_sensor("hdl64") == hdl64()
    assert get_sensor("hdl32") == hdl32()
    sensor = get_sensor(EXAMPLE_YAML)
    assert sensor.name == "vlp16" and sensor.num_rings == 16 and sensor.height == 16
    assert sensor.elevations_deg[0] == 15.0 and isinstance(sensor.elevations_deg, tuple)
    with pytest.raises(InputError, match="hdl64, hdl32"):
        get_sensor("velodyne-128")


def test_yaml_defaults(tmp_path: Path) -> None:
    path = tmp_path / "mini.yaml"
    path.write_text("elevations_deg: [1.0, 0.0, -1.0]\nmin_range: 0.5\nmax_range: 30\n")
    sensor = get_sensor(path)
    assert (sensor.name, sensor.height, sensor.width) == ("mini", 3, 1024)
    assert (sensor.fov_up_deg, sensor.fov_down_deg) == (1.5, -1.5)
    assert isinstance(sensor.max_range, float)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "elevations_deg: [1, 0]\nmin_range: 1\nmax_range: 9\nbeams: 2\n",
            "unknown key.*beams.*valid keys: name",
        ),
        ("elevations_deg: [1, 0]\nmin_range: 1\nmax_range: far\n", "key 'max_range' expects number"),
        ("elevations_deg: [1, 0]\nmin_range: 1\nmax_range: 9\nheight: 2.5\n", "key 'height' expects int"),
        ("elevations_deg: [1, up]\nmin_range: 1\nmax_range: 9\n", "key 'elevations_deg' expects list"),
        ("elevations_deg: [1, 0]\nmin_range: 1\nmax_range: 9\nname: 7\n", "key 'name' expects str"),
        ("elevations_deg: [1, 0]\nmax_range: 9\n", "missing required key.*min_range"),
        ("elevations_deg: [0, 1]\nmin_range: 1\nmax_range: 9\n", "strictly decreasing"),
        ("elevations_deg: [1, 0]\nmin_range: 10\nmax_range: 9\n", "min_range < max_range"),
        ("- 1\n- 2\n", "expected a mapping"),
        ("elevations_deg: [1, 0\n", "not valid yaml"),
    ],
)
def test_yaml_bad_input(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=match) as error:
        get_sensor(path)
    assert "bad.yaml" in str(error.value) and "\n" not in str(error.value)


def test_missing_yaml_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read sensor file"):
        get_sensor(tmp_path / "absent.yaml")


def test_sensor_is_frozen() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        hdl64().max_range = 100.0  # type: ignore[misc]
    assert isinstance(hash(hdl64()), int)
    with pytest.raises(InputError, match="min_range"):
        Sensor("bad", (1.0, 0.0), 0.0, 10.0, 2, 8, 2.0, -2.0)


def test_intensity_response_is_the_identity_by_default(tmp_path: Path) -> None:
    path = tmp_path / "mini.yaml"
    path.write_text("elevations_deg: [1.0, 0.0, -1.0]\nmin_range: 0.5\nmax_range: 30\n")
    remission = np.round(np.linspace(0.0, 0.99, 100), 2).astype(np.float32)  # KITTI's 0.01 steps
    for sensor in (hdl64(), get_sensor(EXAMPLE_YAML), get_sensor(path)):
        assert sensor.reports_remission, sensor.name
        out = intensity_response(sensor, remission)
        assert out.dtype == np.float32 and np.array_equal(out, remission)
    assert not hdl32().reports_remission


@pytest.mark.parametrize(
    "sensor", [hdl32(), dataclasses.replace(hdl64(), intensity_floor=0.2, intensity_gain=3.0, intensity_gamma=0.4)]
)
def test_intensity_response_is_monotone_into_the_unit_interval(sensor: Sensor) -> None:
    remission = np.linspace(-0.1, 1.1, 1201, dtype=np.float32)  # out-of-range values are clipped first
    out = intensity_response(sensor, remission)
    assert np.all(np.diff(out) >= 0) and out.min() >= 0.0 and out.max() <= 1.0
    inside = intensity_response(sensor, np.linspace(0.0, 1.0, 101))
    assert np.all(np.diff(inside[inside < 1.0]) > 0)  # strictly increasing until it saturates


def test_hdl32_response_golden_values() -> None:
    out = intensity_response(hdl32(), np.array([0.0, 0.28, 0.5, 1.0], dtype=np.float32))
    np.testing.assert_allclose(out, [0.009, 0.0446, 0.1779, 1.0], atol=5e-4)  # floor, median, middle, saturated


def test_fit_intensity_response_recovers_a_known_response(rng: np.random.Generator) -> None:
    remission = rng.beta(4.0, 8.0, 200_000)
    truth = Sensor("truth", (1.0, 0.0), 1.0, 9.0, 2, 8, 2.0, -2.0, 0.02, 1.3, 2.5)
    floor, gain, gamma = fit_intensity_response(remission, intensity_response(truth, remission))
    np.testing.assert_allclose([floor, gain, gamma], [0.02, 1.3, 2.5], rtol=0.02, atol=1e-3)


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("intensity_floor", 1.0, "0 <= intensity_floor < 1"),
        ("intensity_floor", -0.1, "0 <= intensity_floor < 1"),
        ("intensity_gain", 0.0, "intensity_gain must be a finite number > 0"),
        ("intensity_gamma", float("nan"), "intensity_gamma must be a finite number > 0"),
    ],
)
def test_intensity_response_bad_values(key: str, value: float, match: str) -> None:
    with pytest.raises(InputError, match=match):
        dataclasses.replace(hdl64(), **{key: value})


def test_intensity_response_from_yaml(tmp_path: Path) -> None:
    path = tmp_path / "dim.yaml"
    path.write_text("elevations_deg: [1, 0]\nmin_range: 1\nmax_range: 9\nintensity_floor: 0.01\nintensity_gamma: 2\n")
    sensor = get_sensor(path)
    assert (sensor.intensity_floor, sensor.intensity_gain, sensor.intensity_gamma) == (0.01, 1.0, 2.0)
    assert intensity_response(sensor, np.array([0.5]))[0] == pytest.approx(0.26)
