"""Beam count from the order of a scan's points: ring by ring (KITTI files) and firing by firing (nuScenes files),
on synthetic sweeps of known beam count and on the real scans; a mismatch with the projecting sensor warns."""

from __future__ import annotations

import logging
import subprocess
import sys

import numpy as np
import pytest

from u4d_aug.data.beams import beams_from_firing_order, beams_from_ring_order, check_beams, estimate_beams
from u4d_aug.data.formats import read_kitti_scan, read_nuscenes_scan
from u4d_aug.data.sensors import get_sensor


def sweep(beams: int, columns: int, order: str, rng: np.random.Generator, dropout: float = 0.0) -> np.ndarray:
    """Points (N, 4) of a spinning sensor over [-25, 3] degrees, `order` 'ring' (ring by ring) or 'firing'."""
    elevation = np.radians(np.linspace(-25.0, 3.0, beams))[:, None]  # (beams, 1) bottom to top
    azimuth = np.linspace(np.pi, -np.pi, columns, endpoint=False)[None, :]  # (1, columns) clockwise from behind
    distance = rng.uniform(5.0, 40.0, (beams, columns))
    xyz = np.stack(
        [distance * np.cos(elevation) * np.cos(azimuth), distance * np.cos(elevation) * np.sin(azimuth),
         distance * np.sin(elevation)], axis=-1,
    )  # fmt: skip
    points = np.concatenate([xyz, rng.uniform(0, 1, (beams, columns, 1))], axis=-1).astype(np.float32)
    keep = rng.uniform(size=(beams, columns)) >= dropout
    if order == "ring":  # ring by ring, top ring first as in KITTI files
        return points[::-1][keep[::-1]]
    return points.transpose(1, 0, 2)[keep.T]  # one firing (bottom to top) per azimuth step


@pytest.mark.parametrize("beams", [16, 32, 64, 128])
def test_synthetic_sweeps_give_their_beam_count(beams):
    rng = np.random.default_rng(beams)
    ring = sweep(beams, 1024, "ring", rng, dropout=0.02)
    firing = sweep(beams, 1024, "firing", rng, dropout=0.02)
    assert beams_from_ring_order(ring) == beams
    assert beams_from_firing_order(firing) == beams
    assert beams_from_firing_order(ring) is None  # a ring-order scan shows no firing groups
    assert estimate_beams(ring) == estimate_beams(firing) == beams
    assert estimate_beams(ring[rng.permutation(len(ring))]) is None  # no order, no estimate, no check
    assert estimate_beams(firing[rng.permutation(len(firing))]) is None
    lossy = sweep(beams, 1024, "firing", rng, dropout=0.1)  # full firings rare: a little low, never a mismatch
    assert 0.9 * beams <= beams_from_firing_order(lossy) <= beams


def test_real_kitti_scans_read_as_64_beams(real_root):
    for path in sorted((real_root / "semantickitti" / "sequences" / "00" / "velodyne").glob("*.bin")):
        beams = estimate_beams(read_kitti_scan(path))
        assert beams is not None and 64 <= beams <= 72, (path.name, beams)  # a few wraps next to the sensor


def test_real_nuscenes_keyframe_reads_as_32_beams(real_root):
    path = next((real_root / "nuscenes_mmdet3d_demo" / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    scan = read_nuscenes_scan(path)  # 8k ego returns within 1 m removed: many firings lose points
    assert beams_from_firing_order(scan.points) == 32
    assert estimate_beams(scan.points, scan.ring) == 32
    raw = read_nuscenes_scan(path, remove_close=0).points
    assert beams_from_firing_order(raw) == 32


def test_mismatch_warns_and_a_match_is_silent(real_root, caplog):
    kitti = read_kitti_scan(real_root / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin")
    nusc = read_nuscenes_scan(next((real_root / "nuscenes_mmdet3d_demo" / "samples" / "LIDAR_TOP").glob("*.pcd.bin")))
    hdl64, hdl32 = get_sensor("hdl64"), get_sensor("hdl32")
    with caplog.at_level(logging.WARNING, logger="u4d_aug.data.beams"):
        check_beams(kitti, hdl64, "kitti.bin")
        check_beams(nusc.points, hdl32, "nusc.pcd.bin")
        assert not caplog.records
        check_beams(nusc.points, hdl64, "nusc.pcd.bin")
        check_beams(kitti, hdl32, "kitti.bin")
    messages = [record.getMessage() for record in caplog.records]
    assert len(messages) == 2
    assert "nusc.pcd.bin: the scan looks recorded by a 32-beam sensor, but it is projected as hdl64" in messages[0]
    assert "empty" in messages[0] and "merged" in messages[1] and "kitti.bin" in messages[1]


def test_show_warns_on_the_wrong_sensor(real_root, tmp_path):
    scan = next((real_root / "nuscenes_mmdet3d_demo" / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    command = [sys.executable, "-m", "u4d_aug.cli", "show", str(scan), "--json"]
    wrong = subprocess.run([*command, "--sensor", "hdl64"], capture_output=True, text=True, timeout=120)
    right = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert wrong.returncode == right.returncode == 0
    assert "looks recorded by a 32-beam sensor, but it is projected as hdl64" in wrong.stderr
    assert "beam" not in right.stderr
