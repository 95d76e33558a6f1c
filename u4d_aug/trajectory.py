"""Ego motion of an L-frame sequence as the condition of the sequence models, and back to poses (U4D §2, 4D).

A sequence's LiDAR poses T_l (L, 4, 4) (sensor to world, `u4d_aug.data.formats.read_poses`) become per-frame
relative motion in the first frame's sensor coordinates, m_l = (x, y, z, yaw) of T_0^{-1} T_l (metres, radians;
m_0 = 0): the SE(2) + z motion a ground vehicle makes (roll and pitch are dropped). `poses_from_motion` is the
inverse for such motion, so a generated sequence conditioned on m gets `poses.txt` = T_0 · pose(m_l), and TTCE can
compare ICP between its frames with exactly the motion it was asked for.
"""

from __future__ import annotations

import numpy as np

from u4d_aug.errors import InputError

POSE_DIM = 4  # (x, y, z, yaw)


def relative_motion(poses: np.ndarray) -> np.ndarray:
    """(L, 4, 4) sensor-to-world poses -> (L, 4) float32 (x, y, z, yaw) of each frame in frame 0's sensor frame."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InputError(f"poses must be (L, 4, 4) homogeneous transforms, got {poses.shape}")
    relative = np.linalg.inv(poses[0]) @ poses  # (L, 4, 4)
    relative[0] = np.eye(4)  # frame 0 in its own frame, exactly (inv(P) @ P leaves ~1e-16 of round-off)
    yaw = np.arctan2(relative[:, 1, 0], relative[:, 0, 0])
    return np.concatenate([relative[:, :3, 3], yaw[:, None]], axis=1).astype(np.float32)


def poses_from_motion(motion: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """(L, 4) (x, y, z, yaw) in frame 0's sensor frame -> (L, 4, 4) poses start · [R_z(yaw) | (x, y, z)]."""
    motion = np.asarray(motion, dtype=np.float64)
    if motion.ndim != 2 or motion.shape[1] != POSE_DIM:
        raise InputError(f"ego motion must be (L, {POSE_DIM}) rows of x, y, z, yaw, got {motion.shape}")
    cos, sin = np.cos(motion[:, 3]), np.sin(motion[:, 3])
    poses = np.tile(np.eye(4), (len(motion), 1, 1))
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = cos, -sin, sin, cos
    poses[:, :3, 3] = motion[:, :3]
    return (np.eye(4) if start is None else np.asarray(start, dtype=np.float64)) @ poses


def straight_motion(frames: int, step: float, yaw_rate: float = 0.0) -> np.ndarray:
    """(L, 4) motion of a vehicle driving `step` metres per frame and turning `yaw_rate` radians per frame."""
    if frames < 1:
        raise InputError(f"frames must be >= 1, got {frames}")
    motion = np.zeros((frames, POSE_DIM), dtype=np.float64)
    for index in range(1, frames):
        yaw = motion[index - 1, 3]
        motion[index, 0] = motion[index - 1, 0] + step * np.cos(yaw)
        motion[index, 1] = motion[index - 1, 1] + step * np.sin(yaw)
        motion[index, 3] = yaw + yaw_rate
    return motion.astype(np.float32)
