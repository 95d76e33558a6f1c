"""Stage 1 starts from its mean image (`u4d generate mean_start_below=...`, `pipeline.MeanStart`): below the threshold
its x̂0 is the stored x0_u mean, so one sampling step at log-SNR −15 returns that mean wherever the mask keeps a pixel,
in the pipeline and in a bank; without the mean start the same step returns the net's own, far from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import plain_settings, save_random_checkpoint
from u4d_aug.bank import BankLayout
from u4d_aug.config import load_config
from u4d_aug.export_weights import export_weights
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.pipeline import MeanStart, generate_stage1, load_generator

HEIGHT = 16  # configs/u4d/tiny.yaml
BELOW = -10.0  # above the first step's log-SNR (−15 at t = 1): that step takes the mean
ATOL = 3e-3  # x̂0 = (x_t − σ ε)/α at α ≈ 5.5e-4 loses ~4e-4 to float32 round-off; the bank stores float16


def hand_mean(low: float, high: float) -> torch.Tensor:
    """A (2, H, 1) per-row mean no net would draw: range rising from `low` to `high`, intensity falling."""
    rows = torch.linspace(0.0, 1.0, HEIGHT)
    return torch.stack([low + (high - low) * rows, 0.5 - 0.4 * rows])[..., None]


STAGE1_MEAN, STAGE2_MEAN = hand_mean(-0.6, 0.6), hand_mean(0.2, 0.3)


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict[str, Path]:
    """Random-weight tiny stage-1 and stage-2 nets exported with the hand-made means as their stored `row_mean`."""
    root = tmp_path_factory.mktemp("mean_start_stage1")
    out = {}
    for stage, key, mean in (("stage1", "x0_u", STAGE1_MEAN), ("stage2", "x0", STAGE2_MEAN)):
        checkpoint = save_random_checkpoint(root / f"{stage}_ckpt.pt", stage)
        out[stage] = root / f"{stage}.pt"
        export_weights(checkpoint, out[stage], data_root=str(root / "nowhere"))  # no scans: no row_mean stored
        state = torch.load(out[stage], weights_only=True)
        assert "row_mean" not in state
        state["row_mean"] = {"key": key, "mean": mean, "source": {"data_root": "hand-made"}}
        torch.save(state, out[stage])
    return out


def kept_pixels(x0_u: torch.Tensor, m_u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(values of x0_u (n, 2, H, W) where m_u (n, 1, H, W) keeps a pixel, the stage-1 mean there)."""
    keep = m_u.bool().expand_as(x0_u)
    return x0_u[keep], STAGE1_MEAN.expand_as(x0_u)[keep]


def bank_stage1(root: Path, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(x0_u (1, 2, H, W), m_u (1, 1, H, W)) that stage 1 drew for sample `index` of a bank."""
    layout = BankLayout(root)
    x0_u = torch.from_numpy(np.load(layout.stage1_path(index)).astype(np.float32))
    return x0_u[None], torch.from_numpy(np.load(layout.mask_path(index)))[None, None]


def test_one_step_of_stage_1_with_the_mean_start_returns_the_mean(exported):
    net, cfg = load_generator(exported["stage1"])
    one_step = plain_settings(1)  # DDIM; the MeanStart below is the mean start
    started = generate_stage1((MeanStart(net, STAGE1_MEAN, BELOW), cfg), 2, torch.Generator().manual_seed(0), one_step)
    values, mean = kept_pixels(started["x0_u"], started["m_u_pred"])
    assert 0 < values.numel() < started["x0_u"].numel()
    assert torch.allclose(values, mean, atol=ATOL)
    # control: the same step without the mean start is the net's clamped x̂0 at α ≈ 0, nowhere near the mean
    own = generate_stage1((net, cfg), 2, torch.Generator().manual_seed(0), one_step)
    assert torch.equal(own["m_u_pred"], started["m_u_pred"])  # the mask head is the net's either way
    values, mean = kept_pixels(own["x0_u"], own["m_u_pred"])
    assert float((values - mean).abs().mean()) > 0.2


def test_the_settings_mean_start_takes_the_mean_stored_in_the_weights_file(exported):
    """`SamplingSettings.mean_start_below`: the loaded net's stored x0_u mean, the MeanStart above without the hand."""
    loaded = load_generator(exported["stage1"])
    assert torch.equal(loaded.net.row_mean_stage1, STAGE1_MEAN) and "row_mean_stage1" not in loaded.net.state_dict()
    by_settings = generate_stage1(
        loaded, 2, torch.Generator().manual_seed(0), plain_settings(1, mean_start_below=BELOW)
    )
    by_hand = generate_stage1(
        (MeanStart(loaded.net, STAGE1_MEAN, BELOW), loaded.config),
        2,
        torch.Generator().manual_seed(0),
        plain_settings(1),
    )
    assert all(torch.equal(by_settings[key], by_hand[key]) for key in ("x0_u", "m_u_pred"))


def test_a_bank_with_the_mean_start_writes_stage_1_s_mean_as_its_x0_u(exported, tmp_path):
    base = [f"stage1={exported['stage1']}", f"stage2={exported['stage2']}", "mode=u4d", "num=2", "device=cpu"]
    base += ["sampler=ddpm", "steps=2", "stage1_steps=1", "stage1_mask_fraction=null", "seed=3"]
    banks, manifests = {}, {}
    for name, extra in (("started", [f"mean_start_below={BELOW}"]), ("own", ["mean_start_below=null"])):
        manifests[name] = generate_bank(
            load_config(GenerateConfig, None, [*base, *extra]), tmp_path / name, progress=False
        )
        assert manifests[name]["complete"]
        banks[name] = [bank_stage1(tmp_path / name, index) for index in range(2)]
    stored = manifests["started"]["mean_start"]["stage1"]
    assert stored["key"] == "x0_u" and stored["stored_in"] == str(exported["stage1"])
    for (x0_u, m_u), (own_x0_u, own_m_u) in zip(banks["started"], banks["own"]):
        values, mean = kept_pixels(x0_u, m_u)
        assert values.numel() > 0 and torch.allclose(values, mean, atol=ATOL)
        values, mean = kept_pixels(own_x0_u, own_m_u)
        assert float((values - mean).abs().mean()) > 0.2  # control: the bank without the mean start
