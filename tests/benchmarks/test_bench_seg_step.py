"""benchmarks/bench_seg_step.py: configs/seg/tiny.yaml on the toy root, point vs voxel loss, 2 timed steps."""

from __future__ import annotations

import json
import math
import sys

import pytest

from tests.tiny_nets import SEG_TINY, load_script


def test_tiny_preset_writes_step_times_of_each_variant(toy_root, tmp_path, monkeypatch):
    out = tmp_path / "seg_step.json"
    variants = [f"data.root={toy_root} loss.level=point", f"data.root={toy_root} loss.level=voxel"]
    argv = ["--config", str(SEG_TINY), "--steps", "2", "--threads", "1", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["bench_seg_step.py", *argv, *(a for v in variants for a in ("--variant", v))])
    assert load_script("bench_seg_step").main() == 0
    result = json.loads(out.read_text())
    assert (result["config"], result["threads"], result["steps"]) == (str(SEG_TINY), 1, 2)
    assert result["machine"]["cores"] >= 1
    rows = result["rows"]
    assert [row["variant"] for row in rows] == variants
    for row in rows:
        assert len(row["step_times"]) == 2 and all(math.isfinite(t) and t > 0 for t in row["step_times"])
        assert row["step_seconds"] == pytest.approx(sorted(row["step_times"])[0] / 2 + sorted(row["step_times"])[1] / 2)
        assert row["steps_per_second"] == pytest.approx(1 / row["step_seconds"])
        assert row["loss_rows_per_step"] > 0 and row["saved_for_backward_mb"] > 0 and "profile" not in row
    assert rows[0]["speedup_vs_first"] == 1.0
    # the voxel loss reads fewer rows than the point loss (0.5 m voxels hold several toy points each)
    assert rows[1]["loss_rows_per_step"] < rows[0]["loss_rows_per_step"]


def test_profile_reports_the_top_operators(toy_root, tmp_path, monkeypatch):
    out = tmp_path / "seg_step.json"
    argv = ["--config", str(SEG_TINY), "--steps", "1", "--threads", "1", "--profile", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["bench_seg_step.py", *argv, "--variant", f"data.root={toy_root}"])
    assert load_script("bench_seg_step").main() == 0
    (row,) = json.loads(out.read_text())["rows"]
    profile = row["profile"]
    assert profile["profiled_seconds"] > 0 and profile["mm_gflop_per_second"] > 0
    assert 0 < len(profile["top_ops"]) <= 12 and sum(op["share"] for op in profile["top_ops"]) <= 1 + 1e-9
