"""Scene propagation along the ego motion: frame 0 of a generated sequence moved into every later frame's range view.

The pose embedding of the MoST nets does not move the scene (benchmarks/results/temporal/temporal_follow.md), so a
sequence that must follow its motion takes the geometry explicitly: frame 0's points, transformed by T_j^-1 T_0 and
projected into frame j's range view, are frame j's known region (x0_u, m_u: the stage-2 condition of U4D, paper §2), and
stage 2 completes the pixels they do not reach (newly seen space, the far field). The world is static under this warp.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from u4d_aug.data.sensors import Sensor
from u4d_aug.errors import InputError
from u4d_aug.range_view import RowMode, project, to_image, unproject


def warp_frame0(x0: Tensor, poses: np.ndarray, sensor: Sensor, row_mode: RowMode = "beam") -> tuple[Tensor, Tensor]:
    """Frame 0's image (2, H, W) in every frame of (L, 4, 4) LiDAR poses -> x0_u (L, 2, H, W), m_u (L, 1, H, W).

    Frame j's pixels hit by frame 0's points moved by T_j^-1 T_0 keep the nearest one (`project`); the others are
    -1 in x0_u and 0 in m_u. Frame 0 is x0 itself, every pixel known (its empty ones stay empty).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if x0.dim() != 3 or x0.shape[0] != 2 or poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InputError(
            f"warp_frame0: expected x0 (2, H, W) and poses (L, 4, 4), got {tuple(x0.shape)}, {poses.shape}"
        )
    height, width = x0.shape[-2:]
    points, valid = unproject(x0.detach().float().cpu(), sensor, row_mode)  # (H, W, 4), (H, W)
    cloud = points[valid].double()  # (M, 4) frame 0's sensor frame
    images, masks = [], []
    for pose in poses:
        moved = torch.from_numpy(np.linalg.solve(pose, poses[0]))  # (4, 4) T_j^-1 T_0: frame 0 -> frame j
        xyz = cloud[:, :3] @ moved[:3, :3].T + moved[:3, 3]  # (M, 3)
        projection = project(torch.cat([xyz, cloud[:, 3:]], dim=1).float(), sensor, height, width, row_mode)
        images.append(to_image(projection, sensor))
        masks.append(projection.mask[None].float())
    images[0], masks[0] = x0.detach().float().cpu(), torch.ones_like(masks[0])  # frame 0 kept whole, empty pixels too
    m_u = torch.stack(masks).to(x0.device, x0.dtype)  # (L, 1, H, W)
    x0_u = torch.stack(images).to(x0.device, x0.dtype)  # (L, 2, H, W)
    return torch.where(m_u.bool(), x0_u, torch.full_like(x0_u, -1.0)), m_u
