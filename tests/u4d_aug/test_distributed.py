"""Two-process torchrun (gloo, CPU) runs of `u4d train-diffusion` (DDP) and `u4d generate` (sharded samples)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from tests.tiny_nets import TINY, torchrun
from tests.tiny_worlds import write_tiny_world
from u4d_aug.bank import read_manifest
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.io import read_jsonl


def test_two_process_training_then_sharded_generation(tmp_path: Path):
    world, probs = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(world, probs)
    run = tmp_path / "baseline"
    torchrun(
        "-m", "u4d_aug.train", str(TINY), "stage=baseline", f"data_root={world}", "steps=2",
        "--out", str(run), "--no-progress",
    )  # fmt: skip
    assert [r["step"] for r in read_jsonl(run / "log.jsonl")] == [2]  # rank 0 logs once per logging step
    ckpt = torch.load(run / "checkpoints" / "step_0000002.pt", weights_only=False)
    assert ckpt["step"] == 2 and all(torch.isfinite(v).all() for v in ckpt["model"].values())

    bank = tmp_path / "bank"
    torchrun(
        "-m", "u4d_aug.generate", str(Path(TINY).with_name("generate_cpu.yaml")), f"baseline={run}",
        "mode=baseline", "num=4", "steps=2", "device=cpu", "--out", str(bank), "--no-progress",
    )  # fmt: skip
    manifest = read_manifest(bank)
    assert manifest["complete"] and [s["index"] for s in manifest["samples"]] == [0, 1, 2, 3]
    scans = sorted((bank / "sequences" / "00" / "velodyne").glob("*.bin"))
    assert [p.name for p in scans] == [f"{i:06d}.bin" for i in range(4)]  # two from each rank
    points = read_kitti_scan(scans[0])
    assert points.shape[1] == 4 and np.isfinite(points).all()
