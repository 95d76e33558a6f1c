"""benchmarks/bench_seg_flops.py: configs/seg/tiny.yaml on the toy root writes each variant's per-conv FLOP rows."""

from __future__ import annotations

import json
import math
import sys

import pytest

from tests.tiny_nets import SEG_TINY, load_script


def test_tiny_preset_writes_forward_flops_per_variant(toy_root, tmp_path, monkeypatch):
    out = tmp_path / "seg_flops.json"
    variants = [f"data.root={toy_root}", f"data.root={toy_root} model.width=0.5"]
    argv = ["--config", str(SEG_TINY), "--batches", "1", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["bench_seg_flops.py", *argv, *(a for v in variants for a in ("--variant", v))])
    assert load_script("bench_seg_flops").main() == 0
    result = json.loads(out.read_text())
    assert result["config"] == str(SEG_TINY) and result["command"].startswith("python benchmarks/bench_seg_flops.py")
    assert [v["variant"] for v in result["variants"]] == variants
    for variant in result["variants"]:
        assert variant["batches"] == 1
        gflop = variant["forward_gflop_per_batch"]
        assert math.isfinite(gflop) and gflop > 0
        rows = variant["convs_of_batch_0"]
        assert rows and sum(r["gflop"] for r in rows) == pytest.approx(gflop, rel=1e-9)
        assert sum(r["share"] for r in rows) == pytest.approx(1.0, rel=1e-9)
        assert all(r["voxels_out"] > 0 and r["c_in"] > 0 and r["c_out"] > 0 and r["kernel_volume"] > 1 for r in rows)
    # a twice-as-wide net does about 4x the multiply-adds (C_in x C_out)
    narrow, wide = (v["forward_gflop_per_batch"] for v in result["variants"])
    assert 2.5 < wide / narrow < 5


def test_missing_data_root_is_an_error_without_output(tmp_path, monkeypatch):
    out = tmp_path / "seg_flops.json"
    argv = ["--config", str(SEG_TINY), "--batches", "1", "--variant", f"data.root={tmp_path / 'none'}"]
    monkeypatch.setattr(sys, "argv", ["bench_seg_flops.py", *argv, "--out", str(out)])
    assert load_script("bench_seg_flops").main() == 2
    assert not out.exists()
