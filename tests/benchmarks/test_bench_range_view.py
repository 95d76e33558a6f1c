"""benchmarks/bench_range_view.py: one repetition of one call on a toy scan writes every config's rates and errors."""

from __future__ import annotations

import json
import math
import sys

import numpy as np

from tests.tiny_nets import load_script
from tests.tiny_worlds import toy_scan
from u4d_aug.data.formats import write_kitti_scan

RATES = ("project_scans_per_s", "unproject_scans_per_s", "project_batch2_scans_per_s")


def test_toy_scan_run_writes_rates_and_roundtrip_errors(tmp_path, monkeypatch):
    scan, out = tmp_path / "000000.bin", tmp_path / "range_view.json"
    write_kitti_scan(scan, toy_scan(np.random.default_rng(0))[0])
    argv = ["--scan", str(scan), "--threads", "1", "--reps", "1", "--calls", "2", "--warmup", "0", "--batch", "2"]
    monkeypatch.setattr(sys, "argv", ["bench_range_view.py", *argv, "--out", str(out)])
    bench = load_script("bench_range_view")
    assert bench.main() == 0
    result = json.loads(out.read_text())
    assert result["benchmark"] == "range_view" and result["points"] == 3000 and result["threads"] == 1
    assert not result["quick"] and result["machine"]["cores"] >= 1
    assert [(r["height"], r["width"], r["row_mode"]) for r in result["results"]] == bench.CONFIGS
    for row in result["results"]:
        for key in RATES:
            assert math.isfinite(row[key]) and row[key] > 0, key
        assert 0 < row["kept_fraction"] <= 1 and 0 <= row["median_error_m"] <= row["p99_error_m"] < math.inf
        assert (row["reps"], row["calls_per_rep"]) == (1, 2)
