"""`u4d show SCAN --ply OUT` (u4d_aug/cli.py): positions, intensity and labels as .ply attributes (open3d tensor API),
atomic."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from u4d_aug.cli import main
from u4d_aug.data.formats import write_kitti_label, write_kitti_scan
from u4d_aug.data.scan import read_scan

o3d = pytest.importorskip("open3d")


def make_scan(folder, labeled: bool):
    """A 200-point SemanticKITTI scan (+ raw labels car / road / vegetation) in velodyne/ and labels/."""
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-20, 20, (200, 3)), rng.uniform(0, 1, (200, 1))], axis=1)
    path = folder / "velodyne" / "000000.bin"
    write_kitti_scan(path, points.astype(np.float32))
    if labeled:
        write_kitti_label(folder / "labels" / "000000.label", rng.choice([10, 40, 70], size=200).astype(np.uint16))
    return path


@pytest.mark.parametrize("labeled", [True, False])
def test_ply_holds_positions_intensity_labels(tmp_path, labeled):
    scan_path = make_scan(tmp_path, labeled)
    ply = tmp_path / "out" / "scan.ply"
    old = os.umask(0o022)
    try:
        assert main(["show", str(scan_path), "--ply", str(ply)]) == 0
    finally:
        os.umask(old)
    scan = read_scan(scan_path)
    cloud = o3d.t.io.read_point_cloud(str(ply))
    np.testing.assert_array_equal(cloud.point.positions.numpy(), scan.points[:, :3])
    np.testing.assert_array_equal(cloud.point.intensity.numpy()[:, 0], scan.points[:, 3])
    if labeled:
        np.testing.assert_array_equal(cloud.point.labels.numpy()[:, 0], scan.labels)
        assert set(np.unique(scan.labels)) == {0, 8, 14}  # car, road, vegetation train ids
    else:
        assert "labels" not in cloud.point
    assert stat.S_IMODE(ply.stat().st_mode) == 0o644
    assert sorted(p.name for p in ply.parent.iterdir()) == ["scan.ply"]  # no temp file left behind


def test_ply_failure_keeps_the_old_file(tmp_path, monkeypatch):
    scan_path = make_scan(tmp_path, labeled=False)
    ply = tmp_path / "scan.ply"
    ply.write_bytes(b"old")
    monkeypatch.setattr(o3d.t.io, "write_point_cloud", lambda *args, **kwargs: False)
    assert main(["show", str(scan_path), "--ply", str(ply)]) == 2
    assert ply.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".ply") == ["scan.ply"]
