"""read_scan: one scan of either format with train-id labels, sensor and ignore id."""

from __future__ import annotations

import numpy as np
import pytest

from u4d_aug.data.formats import write_kitti_label, write_kitti_scan, write_nuscenes_lidarseg, write_nuscenes_scan
from u4d_aug.data.scan import read_scan
from u4d_aug.errors import InputError


def test_kitti_scan_finds_its_labels_folder(tmp_path):
    points = np.array([[5.0, 0, 0, 0.5], [0, 6.0, 0, 0.25], [0, 0, 7.0, 1.0]], np.float32)
    scan_path = tmp_path / "sequences" / "00" / "velodyne" / "000000.bin"
    write_kitti_scan(scan_path, points)
    assert read_scan(scan_path).labels is None
    write_kitti_label(tmp_path / "sequences" / "00" / "labels" / "000000.label", np.array([10, 40, 0]))
    scan = read_scan(scan_path)
    np.testing.assert_array_equal(scan.points, points)
    assert scan.labels.tolist() == [0, 8, 19] and scan.labels.dtype == np.int64  # car, road, unlabeled -> ignore
    assert (scan.sensor, scan.ignore_index) == ("hdl64", 19)


def test_nuscenes_scan_with_its_lidarseg_file(tmp_path):
    points = np.array([[5.0, 0, 0, 0.5], [0.1, 0.1, 0, 0.2], [0, 6.0, 1.0, 1.0]], np.float32)  # row 1: ego return
    write_nuscenes_scan(tmp_path / "a.pcd.bin", points, np.array([0, 1, 2]))
    write_nuscenes_lidarseg(tmp_path / "a_lidarseg.bin", np.array([17, 24, 0]))
    scan = read_scan(tmp_path / "a.pcd.bin", tmp_path / "a_lidarseg.bin")
    assert len(scan.points) == 2 and scan.labels.tolist() == [3, 16]  # car = train id 3; noise -> ignore; ego row gone
    assert (scan.sensor, scan.ignore_index) == ("hdl32", 16)
    assert read_scan(tmp_path / "a.pcd.bin").labels is None


def test_missing_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_scan(tmp_path / "nope.bin")


def test_real_kitti_scan(kitti_root):
    scan = read_scan(kitti_root / "sequences" / "00" / "velodyne" / "000000.bin")
    assert scan.points.shape == (124668, 4) and scan.labels.shape == (124668,)
