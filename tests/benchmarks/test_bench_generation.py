"""benchmarks/bench_generation.py: two sampler settings on tiny untrained nets: json keys, ratios from rows."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.tiny_nets import load_script, save_checkpoint
from u4d_aug.data.formats import write_kitti_scan

bench = load_script("bench_generation")


def test_two_samplers_write_methods_and_ratios(tmp_path):
    rng = np.random.default_rng(0)
    for seq in ("00", "01"):
        for i in range(3):
            points = np.concatenate([rng.uniform(-30, 30, (2000, 3)), rng.uniform(0, 1, (2000, 1))], 1)
            write_kitti_scan(tmp_path / "real" / "sequences" / seq / "velodyne" / f"{i:06d}.bin", points.astype("f4"))
    stages = ("stage1", "stage2", "baseline")
    nets = {
        stage: save_checkpoint(tmp_path / f"{stage}.pt", overrides=(f"diffusion.stage={stage}",)) for stage in stages
    }
    out = tmp_path / "gen.json"
    argv = ["--root", str(tmp_path / "real"), "--stage1", str(nets["stage1"]), "--stage2", str(nets["stage2"])]
    argv += ["--baseline", str(nets["baseline"]), "--reference", "00", "--floor", "01", "--num", "2"]
    argv += ["--seeds", "0", "1", "--samplers", "dpmpp2m:2:1", "ddpm:2:1", "--metrics", "points,rangejs"]
    argv += ["--work", str(tmp_path / "work"), "--out", str(out), "--device", "cpu"]
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert bench.main(argv) == 0
    finally:
        torch.set_num_threads(threads)
    result = json.loads(out.read_text())
    assert list(result["samplers"]) == ["dpmpp2m_2_1", "ddpm_2_1"]
    assert result["methods"] == result["samplers"]["dpmpp2m_2_1"]["methods"]  # the first setting is the headline
    for block in result["samplers"].values():
        methods = block["methods"]
        assert set(methods) == {"u4d", "baseline", "floor"}
        for name in methods:
            for metric in ("points", "rangejs"):
                values = methods[name][metric]["values"]
                assert len(values) == 2 and methods[name][metric]["mean"] == pytest.approx(np.mean(values))
        points = methods["u4d"]["points"]["mean"] / methods["floor"]["points"]["mean"]
        assert block["ratios"]["u4d points/floor"] == pytest.approx(points)
        assert methods["floor"]["points"]["mean"] == 2000  # real scans keep their points
        # ... and hold fewer once projected to the nets' range image (at most one point per pixel)
        cfg = torch.load(nets["baseline"], weights_only=True)["config"]
        projected = methods["floor"]["points_projected"]
        assert len(projected["values"]) == 2 and 0 < projected["mean"] <= min(2000, cfg["height"] * cfg["width"])
        assert block["ratios"]["baseline points/floor projected"] == pytest.approx(
            methods["baseline"]["points"]["mean"] / projected["mean"]
        )
    # the floor is the same real scans for both settings; the banks of each setting are their own
    assert result["samplers"]["ddpm_2_1"]["methods"]["floor"] == result["methods"]["floor"]
    assert (tmp_path / "work" / "u4d_ddpm_2_1_s1").is_dir() and (tmp_path / "work" / "baseline_dpmpp2m_2_1_s0").is_dir()
    text = out.with_suffix(".md").read_text()
    assert "## dpmpp2m 2 steps (stage 1: 1)" in text and "u4d points/floor" in text
    assert "projected to the generators' range image" in text


def test_bad_sampler_setting_is_refused(capsys):
    with pytest.raises(SystemExit):
        bench.main(["--root", "x", "--stage1", "a", "--stage2", "b", "--baseline", "c", "--samplers", "ddpm:x"])
    assert "expected NAME:STEPS:STAGE1_STEPS" in capsys.readouterr().err
