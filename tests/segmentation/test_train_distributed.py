"""Two-process torchrun (gloo, CPU) runs of seg-train and seg-predict on the tiny preset."""

from __future__ import annotations

import numpy as np
import torch

from segmentation.predict import probs_path
from tests.tiny_nets import SEG_TINY as TINY
from tests.tiny_nets import torchrun
from u4d_aug.io import read_jsonl


def test_two_process_training_and_sharded_prediction(toy_root, tmp_path):
    out = tmp_path / "run"
    torchrun(
        "-m", "segmentation.train", str(TINY), f"data.root={toy_root}", "optim.steps=4", "eval_every=2",
        "--out", str(out), "--no-progress",
    )  # fmt: skip
    records = read_jsonl(out / "log.jsonl")  # written by rank 0 only: one record per step, not two
    assert [r["step"] for r in records if "loss" in r] == [1, 2, 3, 4]
    evals = [r for r in records if "val_miou" in r]
    assert [r["step"] for r in evals] == [2, 4]
    ckpt = torch.load(out / "model.pt", weights_only=True)
    assert ckpt["step"] == 4 and ckpt["metrics"]["num_scans"] == 3  # val scans gathered from both ranks
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())

    probs_dir = tmp_path / "probs"
    torchrun(
        "-m", "segmentation.predict", str(out / "model.pt"), str(toy_root), "--out", str(probs_dir),
        "--no-progress",
    )  # fmt: skip
    files = sorted(probs_dir.glob("sequences/*/probs/*.npy"))
    assert len(files) == 6  # rank 0 took scans 0, 2, 4 and rank 1 took 1, 3, 5
    probs = np.load(probs_path(probs_dir, "00", "000001"))
    assert probs.dtype == np.float16 and probs.shape[1] == 19
