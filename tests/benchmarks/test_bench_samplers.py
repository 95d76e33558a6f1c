"""benchmarks/bench_samplers.py: a run on a tiny net (the roughness proxy is tested with range_view)."""

from __future__ import annotations

import json

import numpy as np

from tests.tiny_nets import load_script, save_checkpoint
from u4d_aug.data.formats import write_kitti_scan

bench = load_script("bench_samplers")


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
