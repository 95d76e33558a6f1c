"""The contract of a diffusion stage (u4d_aug/stage.py): its training config and checks, the net it builds, the
checkpoint that names both."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from tests.tiny_nets import TINY, TINY_MOST
from u4d_aug.config import load_config
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.stage import (
    CHECKPOINT_KIND,
    DiffusionTrainConfig,
    build_net,
    checkpoint_state,
    config_from_checkpoint,
    diffusion_overrides,
    diffusion_recipe,
)


def tiny(*overrides: str) -> DiffusionTrainConfig:
    """configs/u4d/tiny.yaml + overrides."""
    return load_config(DiffusionTrainConfig, TINY, list(overrides))


@pytest.mark.parametrize(
    ("override", "key"),
    [("optim.lr=.inf", "optim.lr"), ("optim.lr=.nan", "optim.lr"), ("optim.lr=0", "optim.lr"),
     ("ema_decay=.nan", "ema_decay"), ("optim.betas=[0.9, .inf]", "optim.betas[1]"), ("log_every=0", "log_every"),
     ("diffusion.mask_weight=.nan", "diffusion.mask_weight"), ("net.dropout=.inf", "net.dropout")],
)  # fmt: skip
def test_non_finite_or_negative_numbers_are_refused_at_config_time(override, key):
    with pytest.raises(InputError, match=re.escape(key)):
        load_config(DiffusionTrainConfig, TINY, [override])


def test_crop_config_is_checked():
    assert tiny("crop_width=32").crop_width == 32
    for bad in ("crop_width=33", "crop_width=128", "crop_width=-2"):  # not a multiple of 2, wider than 64, negative
        with pytest.raises(InputError, match="crop_width"):
            tiny(bad)
    assert tiny("crop_width=32", "crop_margin=7").crop_margin == 7
    with pytest.raises(InputError, match="below a quarter of crop_width 32"):
        tiny("crop_width=32", "crop_margin=8")
    with pytest.raises(InputError, match="crop_margin: the margin of azimuth crops needs crop_width > 0"):
        tiny("crop_margin=2")


def test_optimizer_and_window_settings_are_checked():
    for overrides, match in (
        (["optim.schedule=linear"], "key 'optim.schedule' must be one of 'constant', 'cosine'"),
        (["optim.min_lr_ratio=1.5"], "optim.min_lr_ratio must be in [0, 1]"),
        (["optim.betas=[0.9, 1.0]"], "optim.betas must be in [0, 1)"),
        (["frames=0"], "frames and frame_stride must be >= 1"),
        (["propagated_share=0.5"], "the propagated condition is stage 2's on windows of frames >= 2"),
        (["diffusion.stage=u4d", "batch_size=1"], "batch_size must be >= 2"),
    ):
        with pytest.raises(InputError, match=re.escape(match)):
            tiny(*overrides)
    assert tiny("diffusion.stage=stage2", "frames=2", "propagated_share=0.5").propagated_share == 0.5


@pytest.mark.parametrize(
    ("stage", "mask_head", "cond_channels"), [("stage1", True, 0), ("stage2", False, 3), ("baseline", False, 0)]
)
def test_the_net_heads_follow_the_stage(stage, mask_head, cond_channels):
    cfg = tiny(f"diffusion.stage={stage}")
    assert (cfg.net.mask_head, cfg.net.cond_channels) == (mask_head, cond_channels)
    net = build_net(cfg)
    assert (net.mask_conv is not None) == mask_head
    # a copy with another stage gets a net config of its own; the original keeps its heads
    other = dataclasses.replace(cfg, diffusion=dataclasses.replace(cfg.diffusion, stage="stage2"))
    assert other.net.cond_channels == 3 and cfg.net.cond_channels == cond_channels


def test_build_net_is_seeded_by_the_config_and_leaves_the_global_rng_alone():
    torch.manual_seed(5)
    a = build_net(tiny())
    drawn = torch.rand(3)
    torch.manual_seed(5)
    assert torch.equal(torch.rand(3), drawn)  # the build drew nothing from the global generator
    same, other = build_net(tiny()), build_net(tiny("seed=1"))
    for name, value in a.state_dict().items():
        assert torch.equal(same.state_dict()[name], value), name
    assert any(not torch.equal(other.state_dict()[name], value) for name, value in a.state_dict().items())


def test_a_checkpoint_names_its_kind_and_config():
    cfg = tiny("diffusion.stage=stage2", "seed=3")
    net = build_net(cfg)
    ckpt = checkpoint_state(cfg, 7, net, EMA(net), elapsed=12.5)
    assert ckpt["kind"] == CHECKPOINT_KIND and ckpt["step"] == 7 and ckpt["elapsed"] == 12.5
    assert ckpt["optimizer"] is None and ckpt["rng"]["seed"] == 3
    assert ckpt["ema"]["params"].keys() == dict(net.named_parameters()).keys()
    assert config_from_checkpoint(ckpt, "run/step.pt") == cfg
    with pytest.raises(InputError, match=re.escape("seg.pt: not a u4d train-diffusion checkpoint")):
        config_from_checkpoint({**ckpt, "kind": "u4d-seg-checkpoint"}, "seg.pt")


def test_diffusion_overrides_give_a_run_its_source_nets_loss():
    source = tiny(
        "diffusion.stage=u4d", "diffusion.cond_noise=0.05", "diffusion.min_snr_gamma=null", "diffusion.train_t_max=1e-5"
    )
    overrides = diffusion_overrides(source.diffusion)
    assert "diffusion.min_snr_gamma=null" in overrides and "diffusion.train_t_max=1.0e-05" in overrides
    assert not any(item.startswith(("diffusion.stage=", "diffusion.most_cv_weight=")) for item in overrides)
    # a MoST fine-tune of another stage preset and MoST term: the same loss as its source, its own stage and CV weight
    most = load_config(
        DiffusionTrainConfig, TINY_MOST, ["diffusion.stage=u4d", "diffusion.most_cv_weight=0.1", *overrides]
    )
    assert diffusion_recipe(most.diffusion) == diffusion_recipe(source.diffusion)
    assert most.diffusion.most_cv_weight == 0.1 and most.diffusion.min_snr_gamma is None
