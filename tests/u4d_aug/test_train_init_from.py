"""`init_from`: a run starts from a trained net's EMA weights; a MoST / ego-motion net started from a single-frame
net is, before its first step, the same function on every frame (its added blocks start as the identity)."""

from __future__ import annotations

import pytest
import torch

from tests.tiny_nets import diffusion_config as tiny_config
from tests.tiny_worlds import write_tiny_world
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.pipeline import load_generator
from u4d_aug.train import build_net, start_from, train

MOST = ("frames=2", "net.most=true", "net.pose_dim=4")


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
