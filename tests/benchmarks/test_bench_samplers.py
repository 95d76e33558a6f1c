"""benchmarks/bench_samplers.py: the roughness / returns proxies on hand-made images, and a run on a tiny net."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.tiny_nets import load_script, save_checkpoint
from u4d_aug.data.formats import write_kitti_scan

bench = load_script("bench_samplers")


def test_roughness_counts_only_steps_between_returns():
    x0 = torch.full((1, 2, 2, 4), -1.0)  # no returns
    x0[0, 0, 0] = torch.tensor([0.0, 0.5, -1.0, 0.2])  # steps 0.5 (both returns), then two steps touching a hole
    x0[0, 0, 1] = torch.tensor([0.1, 0.1, 0.4, -1.0])  # steps 0.0 and 0.3
    rough, returns = bench.roughness_and_returns(x0)
    assert rough == pytest.approx((0.5 + 0.0 + 0.3) / 3) and returns == pytest.approx(6 / 8)


def test_run_on_a_tiny_net(tmp_path):
    save_checkpoint(tmp_path / "base.pt", overrides=("diffusion.stage=baseline",), step=7)
    rng = np.random.default_rng(0)
    for i in range(2):
        points = np.concatenate([rng.uniform(-30, 30, (3000, 3)), rng.uniform(0, 1, (3000, 1))], 1).astype("f4")
        write_kitti_scan(tmp_path / "real" / "sequences" / "00" / "velodyne" / f"{i:06d}.bin", points)
    out = tmp_path / "samplers.json"
    argv = [str(tmp_path / "base.pt"), "--samplers", "ddpm:2", "dpmpp2m-sde:2:logsnr", "--num", "2"]
    assert bench.main([*argv, "--real", str(tmp_path / "real"), "--threads", "1", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["step"] == 7 and [s["sampler"] for s in result["settings"]] == ["ddpm", "dpmpp2m-sde"]
    assert result["settings"][1]["grid"] == "logsnr" and all(s["s_per_scan"] > 0 for s in result["settings"])
    assert 0 < result["real"]["returns"] <= 1
    assert bench.main([*argv[:1], "--samplers", "ddpm", "--real", str(tmp_path / "real"), "--out", str(out)]) == 2
