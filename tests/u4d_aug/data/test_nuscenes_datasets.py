"""Scan and window datasets over a nuScenes root (u4d_aug/data/nuscenes_datasets.py): the real demo keyframe through
hand-written v1.0 tables, frame order and relative poses, scene selection, missing files. The tables themselves are
tested in test_nuscenes.py, whose hand-written tables these tests read."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.u4d_aug.data.test_nuscenes import CALIB_T, EGO_T, EGO_YAW, _one_line, frame, write_tables
from u4d_aug.data.datasets import open_scans, open_sequences
from u4d_aug.data.formats import read_nuscenes_scan, write_nuscenes_lidarseg, write_nuscenes_scan
from u4d_aug.data.labels import NUSCENES_IGNORE
from u4d_aug.data.nuscenes import read_nuscenes_index
from u4d_aug.data.nuscenes_datasets import NuscenesScanDataset, NuscenesSequenceDataset, resolve_scenes
from u4d_aug.data.sensors import hdl32
from u4d_aug.errors import InputError
from u4d_aug.range_view import project

DEMO = "nuscenes_mmdet3d_demo/samples/LIDAR_TOP/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"


@pytest.fixture(scope="session")
def demo_scan(real_root: Path) -> Path:
    path = real_root / DEMO
    if not path.is_file():
        pytest.skip(f"nuScenes demo keyframe not found at {path}")
    return path


def rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def link(root: Path, relative: str, target: Path) -> None:
    """Put the real file into the tmp root as a symbolic link (real data is never copied)."""
    (root / relative).parent.mkdir(parents=True, exist_ok=True)
    os.symlink(target, root / relative)


def test_real_demo_keyframe_through_hand_written_tables(demo_scan: Path, tmp_path: Path) -> None:
    relative = "samples/LIDAR_TOP/" + demo_scan.name
    link(tmp_path, relative, demo_scan)
    write_tables(tmp_path, [frame("sd-demo", relative, 1532402927647951)])
    scans = NuscenesScanDataset(tmp_path, remove_close=0.0)
    assert scans.sequences == ["scene-0061"] and scans.entries == [("scene-0061", "sd-demo")]
    item = scans[0]
    points = item["points"]
    assert points.shape == (34_688, 4) and points.dtype == np.float32 and item["labels"] is None
    assert points[:, 3].min() == 0.0 and points[:, 3].max() == pytest.approx(1.0)  # intensity 0..255 / 255
    assert len(NuscenesScanDataset(tmp_path)[0]["points"]) == 34_688 - 8_029  # remove_close=1.0: ego returns
    # pose: lidar -> ego -> world, written out with rotation matrices instead of quaternions
    lidar_to_ego, ego_to_world = np.eye(4), np.eye(4)
    lidar_to_ego[:3, :3], lidar_to_ego[:3, 3] = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], CALIB_T
    ego_to_world[:3, :3], ego_to_world[:3, 3] = rotation_z(EGO_YAW), EGO_T
    np.testing.assert_allclose(scans.pose("scene-0061", "sd-demo"), ego_to_world @ lidar_to_ego, atol=1e-12)
    pose = scans.pose("scene-0061", "sd-demo")
    world = points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]  # (N, 3) in the global frame
    # the lidar sits 1.84 m above the ego origin on the road: the road around the car comes out at the ego's height
    near = np.linalg.norm(points[:, :2], axis=1) < 15.0
    assert np.median(world[near, 2]) == pytest.approx(EGO_T[2], abs=0.5)
    # 32 rings: the 32x1024 range image in beam rows fills every row, row = 31 - ring beyond 5 m
    ring = read_nuscenes_scan(demo_scan, remove_close=0.0).ring
    assert len(np.unique(ring)) == 32
    projection = project(torch.from_numpy(points), hdl32(), 32, 1024, "beam")
    assert projection.depth.shape == (32, 1024) and bool(projection.mask.any(dim=1).all())
    far = (projection.pixel >= 0).numpy() & (np.linalg.norm(points[:, :3], axis=1) > 5.0)
    rows = projection.pixel.numpy()[far] // 1024
    assert np.mean(rows == 31 - ring[far]) > 0.9


def test_frames_in_time_order_keyframes_sweeps_and_relative_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    frames = []
    for i, timestamp in enumerate([300, 100, 200, 400]):  # listed out of time order
        name = f"{'samples' if i % 2 == 0 else 'sweeps'}/LIDAR_TOP/f{i}.pcd.bin"
        points = rng.uniform(-20, 20, (50, 4)).astype(np.float32)
        points[:, 3] = rng.uniform(0, 1, 50)
        write_nuscenes_scan(tmp_path / name, points, rng.integers(0, 32, 50))
        ego = [10.0 * timestamp / 100, 0.0, 0.0]  # 10 m per 100 us, straight along world +x
        frames.append(frame(f"t{timestamp}", name, timestamp, key=i % 2 == 0, ego_t=ego, ego_yaw=0.0))
    write_tables(tmp_path, frames)
    assert [f.token for f in read_nuscenes_index(tmp_path).scenes["scene-0061"]] == ["t100", "t200", "t300", "t400"]
    assert [f for _, f in NuscenesScanDataset(tmp_path).entries] == ["t200", "t300"]  # the keyframes, in time order
    assert [f for _, f in NuscenesScanDataset(tmp_path, sweeps=True).entries] == ["t100", "t200", "t300", "t400"]
    windows = NuscenesSequenceDataset(tmp_path, 2, sweeps=True, stride=2)
    assert len(windows) == 2 and windows[0]["frames"] == ["t100", "t300"]
    # ego 20 m further along world +x = 20 m along the lidar's forward +y (the lidar is turned by -90 deg)
    np.testing.assert_allclose(windows[0]["poses"][1][:3, 3], [0.0, 20.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(windows[0]["poses"][0], np.eye(4), atol=1e-12)
    assert open_sequences(tmp_path, 2, data_format="nuscenes").frames == {"scene-0061": ["t200", "t300"]}


def test_scene_selection_by_name_number_and_range(tmp_path: Path) -> None:
    frames = [frame("a", "samples/LIDAR_TOP/a.pcd.bin", 1)]
    write_tables(tmp_path, frames)
    for sequences in (None, "scene-0061", [61], ["61"], "1-100", ["60-61", "scene-0061"]):
        assert NuscenesScanDataset(tmp_path, sequences).sequences == ["scene-0061"]
    with pytest.raises(InputError, match=r"scene.json: no scene 'scene-0062'"):
        NuscenesScanDataset(tmp_path, [62])
    with pytest.raises(InputError, match=r"no scene numbered 100..200"):
        NuscenesScanDataset(tmp_path, "100-200")
    with pytest.raises(InputError, match=r"'train' names a SemanticKITTI split"):
        open_scans(tmp_path, "train", data_format="nuscenes")


def test_missing_scan_and_lidarseg_files_and_a_length_mismatch(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(-20, 20, (40, 4)).astype(np.float32)
    points[:, 3] = 0.5
    write_nuscenes_scan(tmp_path / "samples/LIDAR_TOP/a.pcd.bin", points, np.zeros(40))
    write_tables(tmp_path, [frame("sd1", "samples/LIDAR_TOP/a.pcd.bin", 1, lidarseg="lidarseg/sd1_lidarseg.bin"),
                            frame("sd2", "samples/LIDAR_TOP/b.pcd.bin", 2)])  # fmt: skip
    scans = NuscenesScanDataset(tmp_path, remove_close=0.0)
    _one_line(r"sd1_lidarseg.bin: lidarseg file of sample_data 'sd1' \(lidarseg.json\) not found",
              scans.__getitem__, 0)  # fmt: skip
    write_nuscenes_lidarseg(tmp_path / "lidarseg/sd1_lidarseg.bin", np.full(39, 17))
    _one_line(r"sd1_lidarseg.bin: 39 labels but the scan has 40 points", scans.__getitem__, 0)
    write_nuscenes_lidarseg(tmp_path / "lidarseg/sd1_lidarseg.bin", np.full(40, 17))
    assert (scans[0]["labels"] == 3).all()  # vehicle.car -> car
    assert NuscenesScanDataset(tmp_path, labeled_only=True).entries == [("scene-0061", "sd1")]
    _one_line(r"b.pcd.bin: scan file of sample_data 'sd2' \(scene scene-0061\) not found", scans.__getitem__, 1)
    assert scans.label_set.ignore_index == NUSCENES_IGNORE


def write_keyframes(root: Path, count: int) -> None:
    """`count` keyframes of 30 random points in scene-0061, 100 us apart, the ego 1 m further along x each."""
    rng = np.random.default_rng(2)
    frames = []
    for i in range(count):
        name = f"samples/LIDAR_TOP/k{i}.pcd.bin"
        points = np.concatenate([rng.uniform(-20, 20, (30, 3)), rng.uniform(0, 1, (30, 1))], axis=1)
        write_nuscenes_scan(root / name, points.astype(np.float32), rng.integers(0, 32, 30))
        frames.append(frame(f"k{i}", name, 100 * (i + 1), ego_t=[float(i), 0.0, 0.0], ego_yaw=0.0))
    write_tables(root, frames)


def test_windows_need_enough_frames_and_may_go_without_poses(tmp_path: Path) -> None:
    write_keyframes(tmp_path, 3)
    windows = NuscenesSequenceDataset(tmp_path, 2, with_poses=False)
    assert windows.windows == [("scene-0061", 0), ("scene-0061", 1)]
    item = windows[1]
    assert item["frames"] == ["k1", "k2"] and item["poses"] is None and item["labels"] == [None, None]
    assert [len(points) for points in item["points"]] == [30, 30]
    with pytest.raises(InputError, match="no scene has the 5 frames that a window of 3 x stride 2 needs"):
        NuscenesSequenceDataset(tmp_path, 3, stride=2)
    with pytest.raises(InputError, match="num_frames and stride must be >= 1"):
        NuscenesSequenceDataset(tmp_path, 0)


def test_scene_ranges_must_run_forwards(tmp_path: Path) -> None:
    write_keyframes(tmp_path, 1)
    index = read_nuscenes_index(tmp_path)
    assert resolve_scenes(index, ["61", "scene-0061", 61]) == ["scene-0061"]  # once, however named
    with pytest.raises(InputError, match="sequences: range '70-60' ends before it starts"):
        resolve_scenes(index, "70-60")
