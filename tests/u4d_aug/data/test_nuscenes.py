"""nuScenes v1.0 tables (u4d_aug/data/nuscenes.py): poses, hand-written tables read back, the writer as the reader's
inverse, bad tables. The datasets over them are tested in test_nuscenes_datasets.py."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from u4d_aug.data.nuscenes import (
    LidarFrame,
    matrix_to_quaternion,
    pose_matrix,
    pose_parts,
    quaternion_to_matrix,
    read_nuscenes_index,
    write_nuscenes_tables,
)
from u4d_aug.data.nuscenes_datasets import NuscenesScanDataset
from u4d_aug.errors import InputError

VERSION = "v1.0-trainval"


# ------------------------------------------------------------------------------------------------ hand-written tables


def quaternion_z(angle: float) -> list[float]:
    """w, x, y, z of a turn by `angle` about z."""
    return [math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]


# LIDAR_TOP as nuScenes mounts it: x right, y forward (-90 deg about z), 0.94 m ahead, 1.84 m up
CALIB_T, CALIB_YAW = [0.943713, 0.0, 1.84023], -math.pi / 2
EGO_T, EGO_YAW = [411.3, 1180.9, 0.2], math.radians(30.0)


def write_tables(root: Path, frames: list[dict], version: str = VERSION, **replace) -> Path:
    """Minimal v1.0 tables by hand: one scene 'scene-0061', a camera beside the LiDAR (filtered out), one
    sample_data per entry of `frames` (keys token, filename, timestamp, key, ego_t, ego_yaw, lidarseg)."""
    samples = [f for f in frames if f["key"]]
    tables = {
        "sensor": [
            {"token": "sensor-lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
            {"token": "sensor-cam", "channel": "CAM_FRONT", "modality": "camera"},
        ],
        "calibrated_sensor": [
            {"token": "calib-lidar", "sensor_token": "sensor-lidar", "translation": CALIB_T,
             "rotation": quaternion_z(CALIB_YAW), "camera_intrinsic": []},
            {"token": "calib-cam", "sensor_token": "sensor-cam", "translation": [1.7, 0.0, 1.5],
             "rotation": [0.5, -0.5, 0.5, -0.5], "camera_intrinsic": [[1266.4, 0.0, 816.3]]},
        ],  # fmt: skip
        "scene": [{"token": "scene-a", "log_token": "log-a", "nbr_samples": len(samples), "name": "scene-0061",
                   "first_sample_token": "sample-0", "last_sample_token": "sample-0", "description": "demo"}],
        "sample": [{"token": f"sample-{i}", "timestamp": f["timestamp"], "scene_token": "scene-a", "prev": "",
                    "next": ""} for i, f in enumerate(samples)],
        "ego_pose": [{"token": f"ego-{f['token']}", "timestamp": f["timestamp"], "translation": f["ego_t"],
                      "rotation": quaternion_z(f["ego_yaw"])} for f in frames],
        "sample_data": [{"token": f["token"], "sample_token": "sample-0", "ego_pose_token": f"ego-{f['token']}",
                         "calibrated_sensor_token": "calib-lidar", "timestamp": f["timestamp"], "fileformat": "pcd",
                         "is_key_frame": f["key"], "height": 0, "width": 0, "filename": f["filename"], "prev": "",
                         "next": ""} for f in frames]
        + [{"token": "cam-0", "sample_token": "sample-0", "ego_pose_token": "ego-none",
            "calibrated_sensor_token": "calib-cam", "timestamp": 1, "fileformat": "jpg", "is_key_frame": True,
            "height": 900, "width": 1600, "filename": "samples/CAM_FRONT/x.jpg", "prev": "", "next": ""}],
        "lidarseg": [{"token": f["token"], "sample_data_token": f["token"], "filename": f["lidarseg"]}
                     for f in frames if f.get("lidarseg")],
    }  # fmt: skip
    tables.update(replace)
    folder = root / version
    folder.mkdir(parents=True, exist_ok=True)
    for name, records in tables.items():
        if records is not None:
            (folder / f"{name}.json").write_text(json.dumps(records))
    return root


def frame(token: str, filename: str, timestamp: int, key: bool = True, **extra) -> dict:
    return {"token": token, "filename": filename, "timestamp": timestamp, "key": key, "ego_t": EGO_T,
            "ego_yaw": EGO_YAW, **extra}  # fmt: skip


# ------------------------------------------------------------------------------------------------ geometry


def test_quaternion_round_trip_and_golden() -> None:
    rng = np.random.default_rng(0)
    for q in rng.normal(size=(200, 4)):
        q = q / np.linalg.norm(q) * np.sign(q[0])
        rotation = quaternion_to_matrix(q)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(matrix_to_quaternion(rotation), q, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(quaternion_z(math.pi / 2)), [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
                               atol=1e-15)  # fmt: skip
    np.testing.assert_allclose(matrix_to_quaternion(-np.eye(3) + 2 * np.diag([1, 0, 0])), [0, 1, 0, 0], atol=1e-15)
    pose = pose_matrix([1.0, 2.0, 3.0], quaternion_z(0.3))
    translation, rotation = pose_parts(pose)
    np.testing.assert_allclose(pose_matrix(translation, rotation), pose, atol=1e-15)


# ------------------------------------------------------------------------------------------------ writer


def test_writer_is_the_readers_inverse(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    scenes = {}
    for s, name in enumerate(["scene-0001", "scene-0002"]):
        scenes[name] = []
        for f in range(5):
            ego = pose_matrix(rng.normal(0, 50, 3), rng.normal(size=4) * [1, 0.05, 0.05, 1])
            calib = pose_matrix([0.94, 0.0, 1.84], quaternion_z(-math.pi / 2))
            token = f"{s}{f}".ljust(32, "0")
            scenes[name].append(
                LidarFrame(token, 10**6 * s + 50_000 * f, f % 2 == 0, f"samples/LIDAR_TOP/{token}.pcd.bin", ego,
                           calib, f"lidarseg/{VERSION}/{token}_lidarseg.bin" if f % 2 == 0 else None)
            )  # fmt: skip
    write_nuscenes_tables(tmp_path, {k: v[::-1] for k, v in scenes.items()})  # any order in, time order out
    index = read_nuscenes_index(tmp_path)
    assert list(index.scenes) == ["scene-0001", "scene-0002"]
    for name, frames in scenes.items():
        got = index.scenes[name]
        assert [(f.token, f.timestamp, f.is_key_frame, f.filename, f.lidarseg) for f in got] == [
            (f.token, f.timestamp, f.is_key_frame, f.filename, f.lidarseg) for f in frames
        ]
        for a, b in zip(got, frames):
            np.testing.assert_allclose(a.ego_to_world, b.ego_to_world, atol=1e-9)
            np.testing.assert_allclose(a.lidar_to_world, b.ego_to_world @ b.lidar_to_ego, atol=1e-9)
    written = {p.name for p in (tmp_path / VERSION).iterdir()}
    assert written == {f"{t}.json" for t in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor",
                                              "sensor", "lidarseg", "category", "log")}  # fmt: skip
    samples = json.loads((tmp_path / VERSION / "sample.json").read_text())
    assert len(samples) == 6 and len(json.loads((tmp_path / VERSION / "calibrated_sensor.json").read_text())) == 2
    with pytest.raises(InputError, match="scene 'x' has no keyframe"):
        write_nuscenes_tables(tmp_path / "bad", {"x": [scenes["scene-0001"][1]]})


def test_index_is_read_again_after_a_table_changes(tmp_path: Path) -> None:
    write_tables(tmp_path, [frame("a", "samples/LIDAR_TOP/a.pcd.bin", 1)])
    assert len(read_nuscenes_index(tmp_path).scenes["scene-0061"]) == 1
    assert read_nuscenes_index(tmp_path) is read_nuscenes_index(tmp_path)  # cached
    write_tables(tmp_path, [frame("a", "samples/LIDAR_TOP/a.pcd.bin", 1), frame("b", "sweeps/b.pcd.bin", 2, False)])
    assert len(read_nuscenes_index(tmp_path).scenes["scene-0061"]) == 2


# ------------------------------------------------------------------------------------------------ bad input


def _one_line(match: str, call, *args, **kwargs) -> None:
    with pytest.raises(InputError, match=match) as info:
        call(*args, **kwargs)
    assert "\n" not in str(info.value)


def test_missing_tables_fields_and_references_are_named(tmp_path: Path) -> None:
    ok = [frame("sd1", "samples/LIDAR_TOP/a.pcd.bin", 1)]
    _one_line(r"v1.0-trainval: nuScenes table folder not found; it holds v1.0-mini \(set the version\)",
              NuscenesScanDataset, write_tables(tmp_path / "mini", ok, version="v1.0-mini"))  # fmt: skip
    _one_line(
        r"sample.json: nuScenes table not found", NuscenesScanDataset, write_tables(tmp_path / "a", ok, sample=None)
    )
    no_file = [{k: v for k, v in r.items() if k != "filename"} for r in _sample_data(tmp_path / "a")]
    _one_line(r"sample_data.json: record 'sd1' has no 'filename' field", NuscenesScanDataset,
              write_tables(tmp_path / "b", ok, sample_data=no_file))  # fmt: skip
    dangling = [{**r, "ego_pose_token": "nope"} for r in _sample_data(tmp_path / "a")]
    _one_line(r"sample_data.json: record 'sd1' field 'ego_pose_token' = 'nope' is not a token of ego_pose.json",
              NuscenesScanDataset, write_tables(tmp_path / "c", ok, sample_data=dangling))  # fmt: skip
    empty = [{**r, "filename": ""} for r in _sample_data(tmp_path / "a")]
    _one_line(r"record 'sd1' has an empty 'filename' \(no scan file\)", NuscenesScanDataset,
              write_tables(tmp_path / "d", ok, sample_data=empty))  # fmt: skip
    bad_pose = [{"token": "ego-sd1", "timestamp": 1, "translation": [1, 2], "rotation": [1, 0, 0, 0]}]
    _one_line(r"ego_pose.json: record 'ego-sd1' needs 'translation' \[x, y, z\]", NuscenesScanDataset,
              write_tables(tmp_path / "e", ok, ego_pose=bad_pose))  # fmt: skip
    root = write_tables(tmp_path / "f", ok)
    (root / VERSION / "scene.json").write_text('[{"token": "scene-a", "name": "x"},')
    _one_line(r"scene.json: not valid json \(line 1", NuscenesScanDataset, root)
    category = [{"token": "c", "name": "vehicle.car", "index": 18, "description": ""}]
    _one_line(r"category.json: category 'vehicle.car' has lidarseg index 18, where the 16-class map expects "
              r"'vehicle.construction'", NuscenesScanDataset,
              write_tables(tmp_path / "g", [frame("sd1", "a", 1, lidarseg="l")], category=category))  # fmt: skip
    _one_line(r"no sensor with channel 'LIDAR_TOP'", NuscenesScanDataset,
              write_tables(tmp_path / "h", ok, sensor=[{"token": "s", "channel": "CAM_BACK"}]))  # fmt: skip


def _sample_data(root: Path) -> list[dict]:
    return json.loads((root / VERSION / "sample_data.json").read_text())
