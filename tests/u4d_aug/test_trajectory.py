"""u4d_aug.trajectory: relative ego motion of real poses, and poses rebuilt from motion."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tiny_worlds import REAL_ROOT
from u4d_aug.errors import InputError
from u4d_aug.trajectory import poses_from_motion, relative_motion, straight_motion

REAL = REAL_ROOT / "semantickitti" / "sequences" / "00"


def test_round_trip_of_planar_motion():
    motion = np.array([[0, 0, 0, 0], [1.2, 0.1, 0.02, 0.05], [2.3, 0.35, 0.03, 0.12]], dtype=np.float32)
    start = poses_from_motion(np.array([[5.0, -3.0, 1.0, 0.7]]))[0]  # any world pose of frame 0
    poses = poses_from_motion(motion, start)
    np.testing.assert_allclose(poses[0], start, atol=1e-12)
    np.testing.assert_allclose(relative_motion(poses), motion, atol=1e-6)


def test_straight_and_turning_motion():
    np.testing.assert_allclose(straight_motion(4, 1.2)[:, 0], [0, 1.2, 2.4, 3.6], atol=1e-6)
    left = straight_motion(3, 1.0, yaw_rate=np.pi / 2)  # drive 1 m, turn left 90 degrees, drive 1 m
    np.testing.assert_allclose(left[2], [1.0, 1.0, 0.0, np.pi], atol=1e-6)


def test_real_kitti_poses_give_forward_motion():
    if not REAL.is_dir():
        pytest.skip(f"real SemanticKITTI sample not found at {REAL} (shared data folder absent)")
    from u4d_aug.data.formats import read_calib, read_poses

    poses = read_poses(REAL / "poses.txt", read_calib(REAL / "calib.txt"))[:4]
    motion = relative_motion(poses)
    assert not motion[0].any()  # frame 0 is the origin exactly, as written to a bank's poses.txt
    steps = np.linalg.norm(np.diff(motion[:, :2], axis=0), axis=1)
    assert np.all(steps > 0.3) and np.all(steps < 2.0)  # seq 00 starts at ~0.5-1 m per frame
    assert np.all(motion[1:, 0] > 0) and np.all(np.abs(motion[:, 2]) < 0.2)  # ahead (x forward), level


def test_bad_shapes():
    with pytest.raises(InputError, match="4, 4"):
        relative_motion(np.zeros((3, 3, 4)))
    with pytest.raises(InputError, match="x, y, z, yaw"):
        poses_from_motion(np.zeros((3, 3)))
