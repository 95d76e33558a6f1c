"""benchmarks/bench_semisup.py: --quick on 3000-point real scans, 1 timed step per mode, one subprocess per mode."""

from __future__ import annotations

import json
import math
import sys

import pytest

from tests.tiny_nets import load_script

bench = load_script("bench_semisup")


def test_quick_run_writes_supervised_and_semi_rows(tmp_path, monkeypatch):
    if not (bench.REAL / "sequences" / "00" / "velodyne" / "000000.bin").is_file():
        pytest.skip(f"real scans not found at {bench.REAL}")
    out = tmp_path / "semisup.json"
    argv = ["--quick", "--threads", "1", "--steps", "1", "--max-points", "3000", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["bench_semisup.py", *argv])
    assert bench.main() == 0
    result = json.loads(out.read_text())
    assert (result["threads"], result["max_points"], result["preset"]) == (1, 3000, "configs/seg/cpu_semi.yaml")
    assert result["machine"]["cores"] >= 1
    sup, semi = result["rows"]
    assert (sup["mode"], semi["mode"]) == ("supervised", "semi")
    for row in (sup, semi):
        assert row["timed_steps"] == 1 and math.isfinite(row["median_step_s"]) and row["median_step_s"] > 0
        assert row["steps_per_s"] == pytest.approx(1 / row["median_step_s"])
        assert math.isfinite(row["extra_peak_mb"])
    # batch 2 of 3000-point scans; semi adds 2 unlabeled scans
    assert (sup["input_points_per_step"], semi["input_points_per_step"]) == (6000, 12000)
    ratio = result["semi_over_supervised_step_time"]
    assert ratio == pytest.approx(semi["median_step_s"] / sup["median_step_s"]) and ratio > 0
