"""Scene propagation: a real SemanticKITTI scan moved along known poses into later frames' range views follows those
poses under TTCE's ICP; generated sequences keep the warped pixels and complete the rest."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import TINY_MOST, plain_settings, save_checkpoint
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.data.sensors import hdl64
from u4d_aug.errors import InputError
from u4d_aug.metrics.temporal import icp_translations
from u4d_aug.pipeline import generate_baseline, generate_baseline_propagated, generate_u4d_propagated, load_generator
from u4d_aug.propagate import warp_frame0
from u4d_aug.range_view import project, to_image, unproject
from u4d_aug.trajectory import poses_from_motion, straight_motion


def test_a_real_scan_moved_along_poses_follows_them(kitti_root: Path) -> None:
    scan = read_kitti_scan(kitti_root / "sequences" / "00" / "velodyne" / "000000.bin")
    sensor = hdl64()
    x0 = to_image(project(torch.from_numpy(scan), sensor), sensor)  # (2, 64, 1024)
    # (4, 4, 4): 0.7 m per frame, turning (k = 3 is 2.1 m, within reach of ICP from the identity, as in seq 00)
    poses = poses_from_motion(straight_motion(4, 0.7, yaw_rate=0.02))
    x0_u, m_u = warp_frame0(x0, poses, sensor)
    assert x0_u.shape == (4, 2, 64, 1024) and m_u.shape == (4, 1, 64, 1024)
    torch.testing.assert_close(x0_u[0], x0)  # frame 0 as it is, every pixel known
    torch.testing.assert_close(m_u[0], torch.ones_like(m_u[0]))
    assert (x0_u[:, 0][~m_u[:, 0].bool()] == -1).all()
    coverage = m_u[1:].mean(dim=(1, 2, 3))  # frames 1-3: the share of pixels frame 0's points reach
    returns = float((x0[0] > -1).float().mean())
    assert (coverage > 0.5 * returns).all() and (coverage <= returns).all()
    clouds = [p[v].numpy() for p, v in zip(*unproject(x0_u, sensor))]
    pairs = icp_translations(clouds, poses, intervals=(1, 3))
    for k, (estimate, truth) in pairs.items():
        gain = float(np.sum(estimate * truth) / np.sum(truth * truth))
        assert gain == pytest.approx(1.0, abs=0.1), k  # the warped frames move as the poses say
        assert np.abs(estimate - truth).mean() < 0.1


def randomize(net) -> None:
    """Random weights everywhere, so a completion is not trivially empty."""
    weights = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=weights) * 0.1)


def test_propagated_sequences_keep_the_warped_pixels(tmp_path: Path) -> None:
    loaded = {}
    for stage in ("stage1", "stage2"):
        overrides = (f"diffusion.stage={stage}", "net.pose_dim=4")
        loaded[stage] = load_generator(save_checkpoint(tmp_path / f"{stage}.pt", TINY_MOST, overrides, 1, randomize))
    motion = straight_motion(3, 2.0)  # (3, 4)
    poses = poses_from_motion(motion)[None]  # (1, 3, 4, 4)
    out = generate_u4d_propagated(
        loaded["stage1"], loaded["stage2"], 1, torch.Generator().manual_seed(0), poses, plain_settings(2),
        motion=torch.from_numpy(motion)[None],
    )  # fmt: skip
    x0, x0_u, m_u = out["x0"], out["x0_u"], out["m_u_pred"]
    assert x0.shape == (1, 3, 2, 16, 64) and m_u.shape == (1, 3, 1, 16, 64)
    known = m_u.bool().expand_as(x0)
    torch.testing.assert_close(x0[known], x0_u[known])  # the warped region is kept as it is
    sensor = hdl64()
    expected_u, expected_m = warp_frame0(x0[0, 0], poses[0], sensor, loaded["stage2"][1].row_mode)
    torch.testing.assert_close(m_u[0], expected_m)  # and it is frame 0 moved along the poses
    torch.testing.assert_close(x0_u[0], expected_u)
    with pytest.raises(InputError, match="propagation needs poses"):
        generate_u4d_propagated(loaded["stage1"], loaded["stage2"], 2, torch.Generator(), poses, plain_settings(2))
    with pytest.raises(InputError, match="warp_frame0: expected"):
        warp_frame0(x0[0], poses[0], sensor)


def test_propagated_baseline_sequences_inpaint_around_the_warped_pixels(tmp_path: Path) -> None:
    overrides = ("diffusion.stage=baseline", "net.pose_dim=4")
    loaded = load_generator(save_checkpoint(tmp_path / "baseline.pt", TINY_MOST, overrides, 1, randomize))
    motion = torch.from_numpy(straight_motion(3, 2.0))[None]  # (1, 3, 4)
    poses = poses_from_motion(motion[0].numpy())[None]  # (1, 3, 4, 4)
    ddim = plain_settings(3)
    out = generate_baseline_propagated(loaded, 1, torch.Generator().manual_seed(0), poses, ddim, motion=motion)
    x0, x0_u, m_u = out["x0"], out["x0_u"], out["m_u_pred"]
    assert x0.shape == (1, 3, 2, 16, 64) and m_u.shape == (1, 3, 1, 16, 64)
    plain = generate_baseline(loaded, 1, torch.Generator().manual_seed(0), ddim, 3, motion=motion)["x0"]
    torch.testing.assert_close(x0[:, 0], plain[:, 0])  # frame 0 is the first pass's frame 0
    expected_u, expected_m = warp_frame0(plain[0, 0], poses[0], hdl64(), loaded.config.row_mode)
    torch.testing.assert_close(m_u[0], expected_m)  # the known region is frame 0 moved along the poses
    known = m_u.bool().expand_as(x0)
    torch.testing.assert_close(x0[known], x0_u[known])  # kept as it is
    assert 0 < float(m_u[0, 1:].mean()) < 1  # frames 1, 2: part warped, part inpainted
    assert not torch.allclose(x0[:, 1:][~known[:, 1:]], plain[:, 1:][~known[:, 1:]])  # the rest is drawn anew
    with pytest.raises(InputError, match="propagation needs poses"):
        generate_baseline_propagated(loaded, 2, torch.Generator(), poses, ddim, motion=motion)
