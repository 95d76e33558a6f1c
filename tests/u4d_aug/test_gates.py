"""`u4d gates`: MoST gates recorded at every sampling call, summarised per block and phase, figure + json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import TINY_MOST, save_checkpoint
from u4d_aug.errors import InputError
from u4d_aug.gates import gate_trajectory, summarise_gates


def save_net(path: Path, *overrides: str, temporal_block: str | None = None, trained_branch: str | None = None) -> Path:
    """A tiny MoST checkpoint; `temporal_block` gets a gate bias that picks the temporal branch (α^t ≈ 1);
    `trained_branch` ("enc0:temporal", "mid:spatial", ...) gives that block's branch conv non-zero weights."""

    def bias(net) -> None:
        if temporal_block is not None:
            block = net.most_blocks()[net.most_names.index(temporal_block)]
            with torch.no_grad():
                block.gate[-1].bias.copy_(torch.tensor([-6.0, 6.0]))
        if trained_branch is not None:
            name, branch = trained_branch.split(":")
            conv = getattr(net.most_blocks()[net.most_names.index(name)], branch)
            with torch.no_grad():
                conv.weight.copy_(torch.randn(conv.weight.shape, generator=torch.Generator().manual_seed(1)))

    return save_checkpoint(path, TINY_MOST, overrides, step=1, edit=bias)


def test_gates_are_recorded_per_call_and_block(tmp_path):
    from u4d_aug.pipeline import load_generator

    loaded = load_generator(save_net(tmp_path / "net.pt", temporal_block="mid"))
    trajectory = gate_trajectory(loaded, frames=3, steps=5, generator=torch.Generator().manual_seed(0))
    assert trajectory["blocks"] == ["enc0", "enc1", "mid", "dec1", "dec0"]
    assert trajectory["alpha_t"].shape == (5, 5) and len(trajectory["log_snr"]) == 5
    np.testing.assert_allclose(trajectory["alpha_s"] + trajectory["alpha_t"], 1.0, atol=1e-6)
    assert trajectory["log_snr"] == sorted(trajectory["log_snr"])  # noisy -> clean
    summary = summarise_gates(trajectory)
    mid = summary["blocks"].index("mid")
    assert summary["mean_alpha_t"][mid] > 0.99  # the biased block picks its temporal branch
    others = [t for i, t in enumerate(summary["mean_alpha_t"]) if i != mid]
    assert all(abs(t - 0.5) < 1e-6 for t in others)  # untrained gates are (½, ½)
    assert set(summary["alpha_t_by_phase"]) == {"high noise", "middle", "low noise"}


def test_update_share_follows_the_branch_that_adds_to_the_residual(tmp_path):
    from u4d_aug.pipeline import load_generator

    loaded = load_generator(save_net(tmp_path / "net.pt", trained_branch="mid:temporal"))
    trajectory = gate_trajectory(loaded, frames=3, steps=4, generator=torch.Generator().manual_seed(0))
    summary = summarise_gates(trajectory)
    mid = summary["blocks"].index("mid")
    assert trajectory["rms_t"].shape == (4, 5) and np.all(trajectory["rms_x"] > 0)
    assert summary["mean_temporal_share"][mid] == 1.0  # only its temporal conv adds anything
    assert summary["mean_update_t_over_x"][mid] > 0 and summary["mean_update_s_over_x"][mid] == 0.0
    assert summary["mean_alpha_t"][mid] == 0.5  # while its gate stays at ½
    others = [share for i, share in enumerate(summary["mean_temporal_share"]) if i != mid]
    assert others == [0.5] * 4  # untrained blocks add nothing: neither branch leads
    assert set(summary["temporal_share_by_phase"]) == {"high noise", "middle", "low noise"}
    assert not any(block.record_updates for block in loaded.net.most_blocks())  # switched off afterwards


def test_cli_writes_figure_and_json(tmp_path, capsys):
    from u4d_aug.cli import main

    net = save_net(tmp_path / "net.pt", "diffusion.stage=stage2", "net.pose_dim=4", temporal_block="enc0")
    png = tmp_path / "gates.png"
    assert main(["gates", str(net), "--png", str(png), "--json", "--steps", "3"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert png.is_file() and png.with_suffix(".json").is_file()
    assert summary["mean_alpha_t"][0] > 0.99 and len(summary["alpha_t"]) == 3


def test_nets_without_gates_are_refused(tmp_path):
    from u4d_aug.pipeline import load_generator

    for overrides in (["net.most=false"], ["net.most_fusion=add"]):
        loaded = load_generator(save_net(tmp_path / f"{overrides[0]}.pt", *overrides))
        with pytest.raises(InputError, match="no gated MoST blocks"):
            gate_trajectory(loaded, 2, 2, torch.Generator())


def test_a_one_net_u4d_samples_the_task_of_its_role(tmp_path, capsys):
    from u4d_aug.cli import main
    from u4d_aug.diffusion import STAGE1_TASK, STAGE2_TASK
    from u4d_aug.pipeline import load_generator

    path = save_net(tmp_path / "u4d.pt", "diffusion.stage=u4d", "net.pose_dim=4", temporal_block="mid")
    loaded = load_generator(path)
    seen: list[torch.Tensor] = []
    loaded.net.task_embed.register_forward_hook(lambda module, args, out: seen.append(args[0].clone()))
    for role, task in (("stage1", STAGE1_TASK), ("stage2", STAGE2_TASK)):
        seen.clear()
        trajectory = gate_trajectory(loaded, 2, 2, torch.Generator().manual_seed(0), role=role)
        assert len(seen) == 2 and all(bool((t == task).all()) for t in seen)  # every call: the task of the role
        assert summarise_gates(trajectory)["mean_alpha_t"][2] > 0.99
    with pytest.raises(InputError, match="--role must be stage1 or stage2"):
        gate_trajectory(loaded, 2, 2, torch.Generator(), role="baseline")
    png = tmp_path / "gates.png"
    assert main(["gates", str(path), "--png", str(png), "--role", "stage1", "--steps", "2"]) == 0
    assert png.is_file() and "mid: alpha_s" in capsys.readouterr().out
