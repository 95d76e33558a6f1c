"""TTCE and CTC on the real SemanticKITTI seq-00 frames 0-5 with their poses, and on hand-made cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from u4d_aug.errors import InputError
from u4d_aug.metrics.temporal import (
    IntervalScores,
    ctc,
    load_kitti_sequence,
    merge_interval_scores,
    relative_pose,
    ttce,
)


@pytest.fixture(scope="module")
def sequence(kitti_root: Path) -> tuple[list[np.ndarray], np.ndarray]:
    return load_kitti_sequence(kitti_root / "sequences" / "00")


def _pose(yaw: float, translation: tuple[float, float, float]) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:3, 3] = translation
    return pose


def test_load_sequence(sequence: tuple[list[np.ndarray], np.ndarray]) -> None:
    scans, poses = sequence
    assert len(scans) == 6 and poses.shape == (6, 4, 4)
    assert all(scan.shape[1] == 4 for scan in scans)
    # The car drives ~0.7 m forward (LiDAR x) per frame.
    assert 0.6 < relative_pose(poses, 0, 1)[0, 3] < 0.8


def test_ttce_real_sequence_recovers_ground_truth(sequence: tuple[list[np.ndarray], np.ndarray]) -> None:
    scans, poses = sequence
    scores = ttce(scans, poses)
    print(f"TTCE real seq 00 frames 0-5: {scores.mean} m, per pair {scores.per_pair}")
    assert len(scores.per_pair[3]) == 3 and len(scores.per_pair[4]) == 2
    assert scores.mean[3] < 0.1
    assert scores.mean[4] < 0.1


def test_ttce_wrong_poses_give_large_error(sequence: tuple[list[np.ndarray], np.ndarray]) -> None:
    scans, poses = sequence
    frozen = np.repeat(poses[:1], len(poses), axis=0)  # claims the car stood still while it drove ~2 m
    scores = ttce(scans[:4], frozen[:4], intervals=(3,), voxel_size=0.5)
    assert scores.mean[3] > 0.5


def test_ctc_identical_aligned_frames_is_zero(sequence: tuple[list[np.ndarray], np.ndarray]) -> None:
    scans, _ = sequence
    points = scans[0]
    # The same world points seen from two sensor poses: frame 1 = frame 0 expressed in a moved sensor frame.
    pose0, pose1 = _pose(0.0, (0.0, 0.0, 0.0)), _pose(0.3, (2.0, -1.0, 0.1))
    world = points[:, :3].astype(np.float64)
    local1 = (world - pose1[:3, 3]) @ pose1[:3, :3]  # T1^-1 applied to world points
    moved = np.concatenate([local1, points[:, 3:]], 1)
    keep = np.linalg.norm(world, axis=1) > 0.2  # both frames must drop the same points
    keep &= np.linalg.norm(local1, axis=1) > 0.2
    scores = ctc([points[keep], moved[keep]], np.stack([pose0, pose1]), intervals=(1,))
    assert scores.mean[1] == pytest.approx(0.0, abs=1e-10)
    same = ctc([points, points], np.stack([pose0, pose0]), intervals=(1,))
    assert same.mean[1] == 0.0


def test_ctc_real_consecutive_frames_small_but_positive(
    sequence: tuple[list[np.ndarray], np.ndarray],
) -> None:
    scans, poses = sequence
    scores = ctc(scans, poses, intervals=(1, 3))
    print(f"CTC real seq 00 frames 0-5: {scores.mean} m^2")
    assert 0.0 < scores.mean[1] < 0.2
    assert scores.mean[1] < scores.mean[3]  # farther frames overlap less
    unaligned = ctc(scans[:2], np.repeat(poses[:1], 2, axis=0), intervals=(1,))
    assert unaligned.mean[1] > scores.per_pair[1][0]  # the ground-truth poses do align the frames


def test_ttce_synthetic_motion_is_recovered(rng: np.random.Generator) -> None:
    # A random box-shaped room seen from two poses; ICP from the identity must find a 0.5 m step.
    walls = rng.uniform(-10, 10, (6000, 3))
    walls[:2000, 0] = 10.0
    walls[2000:4000, 1] = -8.0
    walls[4000:, 2] = -1.5
    pose1 = _pose(0.02, (0.5, 0.1, 0.0))
    local1 = (walls - pose1[:3, 3]) @ pose1[:3, :3]
    scores = ttce([walls, local1], np.stack([np.eye(4), pose1]), intervals=(1,), voxel_size=None)
    assert scores.mean[1] < 1e-3


def test_global_registration_finds_what_icp_from_the_identity_misses(
    sequence: tuple[list[np.ndarray], np.ndarray],
) -> None:
    scans, _ = sequence
    # frame 0 of seq 00 seen from 5 poses 2 m apart, turning: frames 4 apart are 8 m apart, beyond ICP's reach
    poses = np.stack([_pose(0.02 * i, (2.0 * i, 0.1 * i, 0.0)) for i in range(5)])
    world = scans[0][:, :3].astype(np.float64)
    frames = [(world - pose[:3, 3]) @ pose[:3, :3] for pose in poses]  # T_i^-1 applied to frame 0's points
    lc = ttce(frames, poses, intervals=(4,))
    found = ttce(frames, poses, intervals=(4,), registration="global")
    print(
        f"TTCE k=4 over 8 m: ICP from the identity {lc.mean[4]:.3f} m, from global registration {found.mean[4]:.4f} m"
    )
    assert lc.mean[4] > 1.0  # ICP from the identity stops far from the 8 m step
    assert found.mean[4] < 0.02
    again = ttce(frames, poses, intervals=(4,), registration="global")
    assert again.per_pair == found.per_pair  # RANSAC is seeded per pair
    with pytest.raises(InputError, match="registration: expected one of icp, global"):
        ttce(frames, poses, intervals=(4,), registration="ransac")  # type: ignore[arg-type]


def test_intervals_beyond_sequence_and_merge() -> None:
    points = np.random.default_rng(0).uniform(-5, 5, (200, 3))
    scores = ctc([points, points], np.stack([np.eye(4)] * 2), intervals=(1, 3))
    assert scores.per_pair[3] == [] and np.isnan(scores.mean[3])
    merged = merge_interval_scores(
        [
            IntervalScores(mean={1: 1.0}, per_pair={1: [1.0]}),
            IntervalScores(mean={1: 3.0}, per_pair={1: [2.0, 4.0]}),
        ]
    )
    assert merged.mean[1] == pytest.approx(7.0 / 3.0)
    assert merged.per_pair[1] == [1.0, 2.0, 4.0]


def test_bad_inputs_raise_input_error() -> None:
    points = np.zeros((10, 4), np.float32)
    with pytest.raises(InputError, match="one pose per scan"):
        ctc([points, points], np.stack([np.eye(4)] * 3))
    with pytest.raises(InputError, match=r"\(T, 4, 4\)"):
        ttce([points], np.eye(4))
    with pytest.raises(InputError, match="positive"):
        ctc([points], np.eye(4)[None], intervals=(0,))
    with pytest.raises(InputError, match=r"scan 1"):
        ctc([points, np.zeros((3, 2))], np.stack([np.eye(4)] * 2))
    with pytest.raises(InputError, match="velodyne"):
        load_kitti_sequence(Path("/nonexistent"))
