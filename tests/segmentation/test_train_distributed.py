"""Two-process torchrun (gloo, CPU) runs of seg-train (supervised, semi) and seg-predict on the tiny presets, against
one process."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from segmentation.batches import TrainBatches, train_class_counts, train_scans
from segmentation.config import SegTrainConfig
from segmentation.losses import class_weights
from segmentation.mean_teacher import make_teacher, teacher_mode
from segmentation.models import build_model
from segmentation.optimizer import learning_rate, make_optimizer
from segmentation.predict import predict_root, probs_path
from segmentation.semi import in_burn_in, semi_step, unlabeled_stream, update_teacher
from segmentation.train import _STEP, supervised_step
from tests.tiny_nets import CPU, SEG_TINY_SEMI, torchrun
from tests.tiny_nets import SEG_TINY as TINY
from u4d_aug.config import load_config
from u4d_aug.io import read_jsonl
from u4d_aug.seeding import derived_seed

SLOT_KEYS = ("slots", "points", "labels", "loss_rows", "unlabeled", "unlabeled_labels")  # one entry per batch slot


def two_ranks_in_one_process(cfg: SegTrainConfig) -> tuple[list[float], dict[str, torch.Tensor]]:
    """(mean loss of each step, final weights of the evaluated model: the teacher in mode "semi") of 2 ranks, computed
    in one process: the same initial weights; the one-process global batch of each step, slot j to rank j % 2
    (batch norm over a rank's own scans, as under DDP); the gradient DDP applies ((g_0 + g_1) / 2: each rank's
    halved, then summed); one clipped AdamW step; the teacher's EMA update."""
    scans = train_scans(cfg, CPU)  # the label split the ranks wrote beside the data
    unlabeled = unlabeled_stream(cfg) if cfg.mode == "semi" else None
    class_weight = class_weights(train_class_counts(scans), cfg.loss) if cfg.loss.class_weighting != "none" else None
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model)
    teacher = teacher_mode(make_teacher(model), cfg.semi.bn_mode) if cfg.mode == "semi" else None
    optimizer = make_optimizer(model, cfg.optim)
    batches = TrainBatches(scans, cfg, 0, 1, unlabeled)  # the whole global batch of each step
    model.train()
    losses = []
    for step in range(cfg.optim.steps):
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(step, cfg.optim)
        optimizer.zero_grad(set_to_none=True)
        per_rank = []
        batch = batches[step]
        for rank in range(2):
            share = {"step": step, **{key: batch[key][rank::2] for key in SLOT_KEYS if key in batch}}
            torch.manual_seed(derived_seed(cfg.seed, _STEP, step, rank))  # as each rank seeds its step
            if teacher is None or in_burn_in(cfg.semi, step):
                loss = supervised_step(model, share, cfg, CPU.device, class_weight)["loss"]
            else:
                loss = semi_step(model, teacher, share, cfg, CPU.device, class_weight)["loss"]
            (loss / 2).backward()
            per_rank.append(float(loss.detach()))
        if cfg.optim.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.optim.grad_clip)
        optimizer.step()
        if teacher is not None:
            update_teacher(teacher, model, cfg.semi, step)
        losses.append(sum(per_rank) / 2)
    evaluated = teacher if teacher is not None else model
    return losses, {name: p.detach().clone() for name, p in evaluated.named_parameters()}


def test_two_process_training_and_sharded_prediction(toy_root, tmp_path):
    out = tmp_path / "run"
    overrides = [f"data.root={toy_root}", "optim.steps=4", "eval_every=2"]
    torchrun("-m", "u4d_aug.cli", "seg-train", str(TINY), *overrides, "--out", str(out), "--no-progress")
    records = read_jsonl(out / "log.jsonl")  # written by rank 0 only: one record per step, not two
    assert [r["step"] for r in records if "loss" in r] == [1, 2, 3, 4]
    evals = [r for r in records if "val_miou" in r]
    assert [r["step"] for r in evals] == [2, 4]
    ckpt = torch.load(out / "model.pt", weights_only=True)
    assert ckpt["step"] == 4 and ckpt["metrics"]["num_scans"] == 3  # val scans gathered from both ranks

    # the same data and effective batch in one process: the same weights bit for bit (halving and a sum of two are
    # exact however DDP orders them); the logged losses up to their float32 mean over the ranks
    losses, weights = two_ranks_in_one_process(load_config(SegTrainConfig, TINY, [*overrides, f"out_dir={out}"]))
    np.testing.assert_allclose([r["loss"] for r in records if "loss" in r], losses, rtol=1e-6)
    for name, value in weights.items():
        assert torch.equal(ckpt["model"][name], value), name

    probs_dir = tmp_path / "probs"
    torchrun(
        "-m", "u4d_aug.cli", "seg-predict", str(out / "model.pt"), str(toy_root), "--out", str(probs_dir),
        "--no-progress",
    )  # fmt: skip
    files = sorted(probs_dir.glob("sequences/*/probs/*.npy"))
    assert len(files) == 6  # rank 0 took scans 0, 2, 4 and rank 1 took 1, 3, 5
    probs = np.load(probs_path(probs_dir, "00", "000001"))
    assert probs.dtype == np.float16 and probs.shape[1] == 19
    single = tmp_path / "probs_one_process"  # each scan is predicted alone: sharding changes no probability
    predict_root(out / "model.pt", toy_root, single, dist_info=CPU, progress=False)
    for path in files:
        assert np.array_equal(np.load(path), np.load(single / path.relative_to(probs_dir))), path.name
    assert not list(Path(single).rglob("*.tmp"))


@pytest.mark.slow
@pytest.mark.parametrize("level", ["point", "voxel"])
def test_two_process_semi_training(toy_root, tmp_path, level):
    """torchrun with 2 processes (gloo): one log record per step, the teacher evaluated and saved, and the weights of
    one process running both ranks' shares of the same global batches (LaserMix, teacher, EMA)."""
    out = tmp_path / "ddp"
    overrides = [f"data.root={toy_root}", "optim.steps=2", "eval_every=2", f"loss.level={level}"]
    torchrun("-m", "u4d_aug.cli", "seg-train", str(SEG_TINY_SEMI), *overrides, "--out", str(out), "--no-progress")
    records = [r for r in read_jsonl(out / "log.jsonl") if "loss" in r]
    assert [r["step"] for r in records] == [1, 2]
    ckpt = torch.load(out / "checkpoints" / "step_0000002.pt", weights_only=True)
    final = torch.load(out / "model.pt", weights_only=True)
    assert final["metrics"]["num_scans"] == 3
    assert all(torch.equal(ckpt["ema"][k], final["model"][k]) for k in final["model"])
    cfg = load_config(SegTrainConfig, SEG_TINY_SEMI, [*overrides, f"out_dir={out}"])
    losses, teacher = two_ranks_in_one_process(cfg)
    np.testing.assert_allclose([r["loss"] for r in records], losses, rtol=1e-6)
    for name, value in teacher.items():
        assert torch.equal(final["model"][name], value), name
