"""Two-process torchrun (gloo, CPU) runs of `u4d train-diffusion` (DDP) and `u4d generate` (sharded samples), against
one process."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import TINY, torchrun
from tests.tiny_worlds import write_tiny_world
from u4d_aug.bank import read_manifest
from u4d_aug.batches import _NOISE, RangeImages, batch_indices, make_batch, stage_inputs
from u4d_aug.config import load_config
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.diffusion import GaussianDiffusion
from u4d_aug.ema import EMA
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.io import read_jsonl
from u4d_aug.seeding import derived_seed
from u4d_aug.stage import DiffusionTrainConfig, build_net
from u4d_aug.train import learning_rate, split_stage_override

CPU = torch.device("cpu")


def two_ranks_in_one_process(cfg: DiffusionTrainConfig) -> tuple[list[float], torch.nn.Module, EMA]:
    """(mean loss of each step, net, EMA) of 2 ranks, computed in one process: the same initial weights, rank r on
    its own scans and noise of each step (seeded by (seed, step, r)), the gradient DDP applies ((g_0 + g_1) / 2:
    each rank's halved, then summed), one clipped AdamW step and the EMA update, as the loop of u4d_aug/train.py."""
    assert not cfg.crop_width and not cfg.net.most and not cfg.net.pose_dim  # the plain path of the loop
    images = RangeImages(cfg)
    net = build_net(cfg, CPU)
    diffusion = GaussianDiffusion(net, cfg.diffusion)
    optimizer = torch.optim.AdamW(
        net.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas, weight_decay=cfg.optim.weight_decay
    )
    ema = EMA(net, cfg.ema_decay, cfg.ema_warmup_steps)
    losses = []
    for step in range(cfg.steps):
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(step, cfg.optim, cfg.steps)
        optimizer.zero_grad(set_to_none=True)
        per_rank = []
        for rank in range(2):
            generator = torch.Generator().manual_seed(derived_seed(cfg.seed, _NOISE, step, rank))
            indices = batch_indices(step, rank, len(images), cfg.batch_size, cfg.seed)
            x0, cond, m_u = stage_inputs(cfg.diffusion.stage, make_batch(images, indices, generator, CPU))
            loss = diffusion(x0, cond, m_u, generator)["loss"]
            (loss / 2).backward()
            per_rank.append(float(loss.detach()))
        torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.optim.grad_clip if cfg.optim.grad_clip > 0 else np.inf)
        optimizer.step()
        ema.update(net)
        losses.append(sum(per_rank) / 2)
    return losses, net, ema


def test_two_process_training_then_sharded_generation(tmp_path: Path):
    world, probs = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(world, probs)
    run = tmp_path / "baseline"
    overrides = ["stage=baseline", f"data_root={world}", "steps=2"]
    torchrun("-m", "u4d_aug.cli", "train-diffusion", str(TINY), *overrides, "--out", str(run), "--no-progress")
    log = read_jsonl(run / "log.jsonl")
    assert [r["step"] for r in log] == [2]  # rank 0 logs once per logging step
    ckpt = torch.load(run / "checkpoints" / "step_0000002.pt", weights_only=False)
    assert ckpt["step"] == 2

    # the same scans, noise and effective batch in one process: the same weights and EMA bit for bit (halving and a
    # sum of two are exact however DDP orders them); the logged loss up to its float32 mean over the ranks
    cfg = load_config(DiffusionTrainConfig, TINY, [*split_stage_override(overrides), f"out={run}"])
    assert batch_indices(0, 0, 1000, 4, cfg.seed) != batch_indices(0, 1, 1000, 4, cfg.seed)  # ranks draw apart
    losses, net, ema = two_ranks_in_one_process(cfg)
    assert log[0]["loss"] == pytest.approx(np.mean(losses), rel=1e-6)
    for name, value in net.state_dict().items():
        assert torch.equal(ckpt["model"][name], value), name
    for name, value in ema.params.items():
        assert torch.equal(ckpt["ema"]["params"][name], value), name

    # blocks of batch_size samples, block b on rank b % 2; each sample seeded on its own: the one-process bank
    generate = [str(Path(TINY).with_name("generate_cpu.yaml")), f"baseline={run}", "mode=baseline", "num=4", "steps=2"]
    generate += ["batch_size=2", "device=cpu"]
    bank = tmp_path / "bank"
    torchrun("-m", "u4d_aug.cli", "generate", *generate, "--out", str(bank), "--no-progress")
    manifest = read_manifest(bank)
    assert manifest["complete"] and [s["index"] for s in manifest["samples"]] == [0, 1, 2, 3]
    scans = sorted((bank / "sequences" / "00" / "velodyne").glob("*.bin"))
    assert [p.name for p in scans] == [f"{i:06d}.bin" for i in range(4)]  # two from each rank
    points = read_kitti_scan(scans[0])
    assert points.shape[1] == 4 and np.isfinite(points).all()
    single = tmp_path / "bank_one_process"
    generate_bank(load_config(GenerateConfig, Path(generate[0]), generate[1:]), single, progress=False)
    assert read_manifest(single)["samples"] == manifest["samples"]  # seeds and file digests
    for path in scans:
        assert path.read_bytes() == (single / path.relative_to(bank)).read_bytes(), path.name


def test_cleanup_frees_a_ddp_wrapper_before_leaving_the_group(tmp_path: Path):
    # a DDP wrapper lives in reference cycles; left to the interpreter's exit its reducer would outlive the group
    import gc
    import weakref

    import torch.distributed as dist

    from u4d_aug.distributed import cleanup

    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'store'}", rank=0, world_size=1)

    def train_once() -> weakref.ref:
        model = torch.nn.parallel.DistributedDataParallel(torch.nn.Linear(3, 2))
        model(torch.randn(4, 3)).sum().backward()
        loop = {"model": model}
        loop["loop"] = loop  # the wrapper in a reference cycle (its own hooks make one on a first construction)
        return weakref.ref(model.reducer)

    enabled = gc.isenabled()
    gc.disable()  # as between two automatic collections: only the cycle collector frees the wrapper
    try:
        reducer = train_once()
        assert reducer() is not None  # still held by its cycles after the function returned
        cleanup()
        assert reducer() is None and not dist.is_initialized()
    finally:
        if enabled:
            gc.enable()
        if dist.is_initialized():
            dist.destroy_process_group()
