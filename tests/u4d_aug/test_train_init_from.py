"""`init_from`: a run starts from a trained net's EMA weights; a MoST / ego-motion net started from a single-frame
net is, before its first step, the same function on every frame (its added blocks start as the identity); a one-net
u4d MoST net fine-tuned from a one-net single-frame net trains both tasks, exports and generates sequences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.tiny_nets import REPO, TINY, save_checkpoint
from tests.tiny_nets import diffusion_config as tiny_config
from tests.tiny_worlds import write_posed_world, write_tiny_world
from u4d_aug.bank import BankLayout
from u4d_aug.config import load_config
from u4d_aug.diffusion import STAGE1_TASK, STAGE2_TASK
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.pipeline import load_generator
from u4d_aug.train import build_net, check_source_recipe, start_from, train

MOST = ("frames=2", "net.most=true", "net.pose_dim=4")
U4D_RECIPE = ("diffusion.cond_noise=0.05", "diffusion.min_snr_gamma=null")  # the final single-frame recipe's loss
U4D_MOST = ("frames=4", "net.most=true", "net.pose_dim=4", "batch_size=2")  # one window per task
GENERATE_MOST = REPO / "configs" / "u4d" / "generate_hdl64_most.yaml"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny single-frame baseline trained 3 steps, and its exported float16 weights."""
    base = tmp_path_factory.mktemp("init_from")
    world = (base / "world", base / "probs")
    write_tiny_world(*world)
    run = base / "single"
    train(tiny_config(world, run, "baseline", "steps=3", "checkpoint_every=3"), progress=False)
    export_weights(sorted((run / "checkpoints").glob("step_*.pt"))[-1], base / "single.pt")
    return world, run, base / "single.pt"


@pytest.mark.parametrize(
    ("source", "fusion"),
    [("run", "gating"), ("exported", "gating"), ("run", "cascade"), ("run", "add"), ("run", "concat")],
)
def test_most_net_started_from_a_single_frame_net_computes_the_same(trained, tmp_path, source, fusion):
    """Every MoST fusion of the ablation starts as the identity, so each fine-tune starts from the same function."""
    world, run, exported = trained
    init = str(run if source == "run" else exported)
    cfg = tiny_config(world, tmp_path / "most", "baseline", *MOST, f"net.most_fusion={fusion}", f"init_from={init}")
    net = build_net(cfg).eval()
    added = start_from(net, cfg)
    assert "most_down" in added and "pose_embed" in added and "enc" not in " ".join(added)
    single, _ = load_generator(init)
    gen = torch.Generator().manual_seed(0)
    x_t = torch.randn(2, 2, cfg.net.in_channels, cfg.height, cfg.width, generator=gen)  # (B, L, C, H, W)
    log_snr = torch.tensor([0.5, -1.0])
    motion = torch.randn(2, 2, 4, generator=gen)
    with torch.no_grad():
        eps_seq, _ = net(x_t, log_snr, poses=motion)
        eps_one, _ = single(x_t.flatten(0, 1), log_snr.repeat_interleave(2))
    tolerance = 0.0 if source == "run" else 5e-3  # exported weights are float16 (tests/test_weights.py)
    assert float((eps_seq.flatten(0, 1) - eps_one).abs().max()) <= tolerance
    fresh = build_net(cfg).eval()
    with torch.no_grad():
        assert float((fresh(x_t, log_snr, poses=motion)[0] - eps_seq).abs().max()) > 0.01  # the weights did load


def test_fine_tuning_run_trains_and_resumes_from_its_own_checkpoint(trained, tmp_path):
    world, run, _ = trained
    out = tmp_path / "most"
    seq = ("frames=2", "net.most=true")  # the tiny world has no poses.txt for the ego-motion input
    cfg = tiny_config(world, out, "baseline", *seq, f"init_from={run}", "steps=2", "checkpoint_every=1")
    record = train(cfg, progress=False)
    assert record["step"] == 2 and record["loss"] > 0
    cfg = tiny_config(world, out, "baseline", *seq, f"init_from={run}", "steps=3", "checkpoint_every=1")
    assert train(cfg, resume="last", progress=False)["step"] == 3  # resumes its own weights, not init_from's


def test_other_stage_or_other_net_is_refused(trained, tmp_path):
    world, run, _ = trained
    with pytest.raises(InputError, match="is a baseline net, this run trains stage2"):
        cfg = tiny_config(world, tmp_path / "s2", "stage2", f"init_from={run}")
        start_from(build_net(cfg), cfg)
    with pytest.raises(InputError, match="has tensors this net lacks or shapes unlike its"):
        cfg = tiny_config(world, tmp_path / "wide", "baseline", "net.base_channels=16", f"init_from={run}")
        start_from(build_net(cfg), cfg)


def drawn_outputs(net: torch.nn.Module) -> None:
    """The net's zero-initialised tensors (output convs, residual outputs) drawn at random, so that its ε̂ and mask
    logits depend on its input and task (an untrained net gives ε̂ = 0 whatever they are)."""
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for param in net.parameters():
            if not bool(param.any()):
                param.copy_(0.1 * torch.randn(param.shape, generator=generator))


@pytest.fixture(scope="module")
def trained_u4d(tmp_path_factory):
    """A tiny one-net u4d single-frame net on a world of 5 scans with poses (its output layers drawn at random), as
    exported weights."""
    base = tmp_path_factory.mktemp("init_from_u4d")
    world = (base / "world", base / "probs")
    write_posed_world(*world, num_scans=5)
    overrides = ("diffusion.stage=u4d", *U4D_RECIPE, f"data_root={world[0]}", f"probs_root={world[1]}")
    source = save_checkpoint(base / "single_step.pt", TINY, overrides, step=2, edit=drawn_outputs)
    export_weights(source, base / "single.pt")
    return world, base / "single.pt"


def test_u4d_most_net_started_from_a_one_net_single_frame_net_computes_the_same_for_both_tasks(trained_u4d, tmp_path):
    world, single_path = trained_u4d
    cfg = tiny_config(world, tmp_path / "most", "u4d", *U4D_RECIPE, *U4D_MOST, f"init_from={single_path}")
    net = build_net(cfg).eval()
    assert start_from(net, cfg) == ["most_down", "most_mid", "most_up", "pose_embed"]  # task embedding: the source's
    single, single_cfg = load_generator(single_path)
    gen = torch.Generator().manual_seed(0)
    x_t = torch.randn(2, 4, 2, cfg.height, cfg.width, generator=gen)  # (B, L, C, H, W)
    cond = torch.rand(2, 4, 3, cfg.height, cfg.width, generator=gen) * 2 - 1
    log_snr, task = torch.tensor([0.5, -1.0]), torch.tensor([STAGE1_TASK, STAGE2_TASK])  # a window per task
    motion = torch.randn(2, 4, 4, generator=gen)
    with torch.no_grad():
        eps_seq, mask_seq = net(x_t, log_snr, cond, poses=motion, task=task)
        frames = (x_t.flatten(0, 1), log_snr.repeat_interleave(4), cond.flatten(0, 1))
        eps_one, mask_one = single(*frames, task=task.repeat_interleave(4))  # frame by frame, each its window's task
    assert float((eps_seq.flatten(0, 1) - eps_one).abs().max()) <= 1e-5  # both hold the same float16 weights
    assert float((mask_seq.flatten(0, 1) - mask_one).abs().max()) <= 1e-5
    assert float(eps_one.abs().max()) > 0.1 and float(mask_one.abs().max()) > 0.1  # not a function of nothing
    with torch.no_grad():
        other_task = net(x_t, log_snr, cond, poses=motion, task=1 - task)[0]
    assert float((other_task - eps_seq).abs().max()) > 0.01  # the task embedding reaches the output
    # the fine-tune runs on its source's loss; another one is named (and logged when training starts)
    assert check_source_recipe(single_cfg, cfg) == {}
    plain = tiny_config(world, tmp_path / "plain", "u4d", *U4D_MOST, f"init_from={single_path}")
    assert check_source_recipe(single_cfg, plain) == {"min_snr_gamma": (None, 5.0), "cond_noise": (0.05, 0.0)}


def test_u4d_most_fine_tune_trains_both_tasks_exports_and_generates_sequences(trained_u4d, tmp_path):
    world, single_path = trained_u4d
    out = tmp_path / "most"
    overrides = (f"init_from={single_path}", "steps=2", "checkpoint_every=2", "sample_every=2", "sample_steps=2")
    record = train(tiny_config(world, out, "u4d", *U4D_RECIPE, *U4D_MOST, *overrides), progress=False)
    assert record["step"] == 2
    assert all(np.isfinite(record[k]) for k in ("eps_mse_stage1", "eps_mse_stage2", "mask_bce", "most_cv"))
    assert (out / "samples" / "step_0000002.png").is_file()  # sampled along a straight motion (net.pose_dim)
    exported = export_weights(out, tmp_path / "most.pt")
    assert exported["row_mean"]["key"] == "x0" and exported["row_mean_stage1"]["key"] == "x0_u"
    # `u4d generate configs/u4d/generate_hdl64_most.yaml mode=u4d net=MOST stage1= stage2=`, tiny and short
    short = ["num=1", "steps=2", "stage1_steps=2", "device=cpu", "stage1=", "stage2=", f"net={tmp_path / 'most.pt'}"]
    for propagate in (False, True):
        switch = [f"propagate={str(propagate).lower()}", f"propagate_pin={str(propagate).lower()}"]
        cfg = load_config(GenerateConfig, GENERATE_MOST, ["mode=u4d", *short, *switch])
        bank = tmp_path / f"bank_{propagate}"
        manifest = generate_bank(cfg, bank, progress=False)
        assert manifest["complete"] and manifest["frames"] == 5  # the preset's L, the net trained on 4
        assert manifest["checkpoints"]["stage1"] == manifest["checkpoints"]["stage2"]  # one net, both roles
        assert set(manifest["mean_start"]) == {"stage1", "stage2"}  # each role's stored mean
        assert manifest["sampling"].get("propagate", False) is propagate
        layout = BankLayout(bank, 5)
        assert layout.poses_path(0).is_file() and all(
            layout.scan_path(0, f).is_file() or layout.is_empty(0, f) for f in range(5)
        )
