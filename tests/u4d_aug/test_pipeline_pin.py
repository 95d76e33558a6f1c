"""Pinned propagation (`generate_u4d_propagated(pin_known=True)`, `u4d generate propagate=true propagate_pin=true`):
stage 2's x̂0 is held to the warped pixels at every step, so the pixels it fills differ from an unpinned fill; on nets
with random weights, whose output depends on x_t (untrained nets ignore it and make both fills the same)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from tests.tiny_nets import PLAIN_SAMPLING, TINY_MOST, plain_settings, save_checkpoint
from u4d_aug.bank import BankLayout
from u4d_aug.config import load_config
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.data.sensors import get_sensor
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.pipeline import complete, generate_u4d, generate_u4d_propagated, load_generator
from u4d_aug.propagate import warp_frame0
from u4d_aug.trajectory import poses_from_motion, straight_motion

FRAMES, STEPS, SEED = 3, 3, 5
DDIM = plain_settings(STEPS)  # these nets store no training mean


def randomize(net: nn.Module) -> None:
    """Random weights (seed 0; untrained output convs are zero), a stage-1 mask head keeping about half the pixels."""
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for param in net.parameters():
            param.add_(torch.randn(param.shape, generator=generator) * 0.2)
        if net.mask_conv is not None:
            net.mask_conv.bias.fill_(0.3)


def straight_poses() -> np.ndarray:
    """(1, FRAMES, 4, 4) poses of one sequence driving 1 m per frame straight ahead."""
    return poses_from_motion(straight_motion(FRAMES, 1.0))[None]


def by_hand(stage1, stage2, pin_known: bool) -> dict[str, torch.Tensor]:
    """`generate_u4d_propagated` spelled out with the same draws: frame 0 by U4D, warped along the poses, completed."""
    generator = torch.Generator().manual_seed(SEED)
    first = generate_u4d(stage1, stage2, 1, generator, DDIM, frames=FRAMES)["x0"]  # (1, L, 2, H, W)
    x0_u, m_u = warp_frame0(first[0, 0], straight_poses()[0], get_sensor(stage2.config.sensor), stage2.config.row_mode)
    x0_u, m_u = x0_u[None], m_u[None]  # (1, L, 2|1, H, W)
    filled = complete(stage2, x0_u, m_u, generator, DDIM, pin_known=pin_known)["x0"]
    return {"x0_u": x0_u, "m_u": m_u, "filled": filled, "x0": torch.where(m_u.bool(), x0_u, filled)}


def test_the_pin_holds_stage_2_to_the_warped_pixels_and_changes_the_fill(random_ema_checkpoints):
    stage1, stage2 = load_generator(random_ema_checkpoints["stage1"]), load_generator(random_ema_checkpoints["stage2"])
    runs = {
        pin: generate_u4d_propagated(
            stage1, stage2, 1, torch.Generator().manual_seed(SEED), straight_poses(), DDIM, pin_known=pin
        )
        for pin in (True, False)
    }
    pinned, plain = by_hand(stage1, stage2, True), by_hand(stage1, stage2, False)
    assert torch.equal(runs[True]["x0"], pinned["x0"]) and torch.equal(runs[False]["x0"], plain["x0"])
    assert torch.equal(runs[True]["m_u_pred"], pinned["m_u"])

    known = pinned["m_u"].bool().expand_as(pinned["x0_u"])  # (1, L, 2, H, W)
    later = known[:, 1:]  # frames 1..L-1: the warped part of each, the rest is stage 2's to fill
    assert 0 < int(later.sum()) < later.numel()
    # pinned, stage 2's own sample ends on the warped pixels; unpinned it does not
    assert torch.allclose(pinned["filled"][known], pinned["x0_u"][known], atol=1e-5)
    assert not torch.allclose(plain["filled"][known], plain["x0_u"][known], atol=1e-3)
    # and the pixels it fills around them follow: the two outputs differ where nothing was warped
    assert float((runs[True]["x0"] - runs[False]["x0"])[:, 1:][~later].abs().max()) > 1e-3


@pytest.fixture(scope="module")
def posed_random(tmp_path_factory) -> dict[str, Path]:
    """Random-weight tiny MoST stage-1 and stage-2 checkpoints with an ego-motion input (propagation needs one)."""
    root = tmp_path_factory.mktemp("posed_random")
    return {
        stage: save_checkpoint(
            root / f"{stage}.pt", TINY_MOST, (f"diffusion.stage={stage}", "net.pose_dim=4"), edit=randomize
        )
        for stage in ("stage1", "stage2")
    }


def test_a_pinned_bank_is_filled_otherwise_than_a_plain_one(posed_random, tmp_path):
    np.save(tmp_path / "straight.npy", straight_motion(FRAMES, 1.0))
    paths = [f"stage1={posed_random['stage1']}", f"stage2={posed_random['stage2']}"]
    base = [*paths, "steps=2", "sampler=ddim", *PLAIN_SAMPLING, "device=cpu", "seed=7", "num=1", f"frames={FRAMES}"]
    base += [f"motion_file={tmp_path / 'straight.npy'}", "propagate=true"]
    scans = {}
    for name, extra in (("plain", []), ("pinned", ["propagate_pin=true"])):
        generate_bank(load_config(GenerateConfig, None, [*base, *extra]), tmp_path / name, progress=False)
        layout = BankLayout(tmp_path / name, FRAMES)
        scans[name] = [read_kitti_scan(layout.scan_path(0, frame)) for frame in range(FRAMES)]
    assert np.array_equal(scans["plain"][0], scans["pinned"][0])  # frame 0: the same U4D draw
    for frame in range(1, FRAMES):  # the propagated frames: stage 2 filled them pinned in one bank only
        assert not np.array_equal(scans["plain"][frame], scans["pinned"][frame]), frame
