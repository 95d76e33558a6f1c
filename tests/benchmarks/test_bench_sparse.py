"""benchmarks/bench_sparse.py: --quick --skip-train, 1 channel, 1 repetition: sparse vs dense submanifold conv."""

from __future__ import annotations

import json
import math
import sys

import pytest

from tests.tiny_nets import load_script

bench = load_script("bench_sparse")


def test_quick_conv_table_matches_dense(tmp_path, monkeypatch):
    if not (bench.SEQUENCE / "velodyne" / "000000.bin").is_file():
        pytest.skip(f"real scans not found at {bench.SEQUENCE}")
    out = tmp_path / "sparse.json"
    argv = ["--quick", "--skip-train", "--reps", "1", "--channels", "1", "--threads", "1", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["bench_sparse.py", *argv])
    assert bench.main() == 0
    result = json.loads(out.read_text())
    assert result["threads"] == 1 and result["train"] == [] and result["machine"]["cores"] >= 1
    assert [(row["voxel_size"], row["op"], row["channels"]) for row in result["conv"]] == [
        (0.2, "sub", 1),
        (0.1, "sub", 1),
    ]
    grids = {0.2: [256, 256, 32], 0.1: [512, 512, 64]}
    for row in result["conv"]:
        sparse, dense = row["sparse"], row["dense"]
        for seconds in (sparse["seconds"], sparse["cold_seconds"], dense["seconds"]):
            assert math.isfinite(seconds) and seconds > 0
        assert dense["cold_seconds"] is None and sparse["grid"] == dense["grid"] == grids[row["voxel_size"]]
        assert sparse["voxels_in"] == dense["voxels_in"] == sparse["sites_out"] > 0
        assert row["speedup"] == pytest.approx(dense["seconds"] / sparse["seconds"])
        assert row["max_abs_value"] > 0 and row["max_abs_diff"] <= 1e-4 * row["max_abs_value"]
    assert result["conv"][1]["sparse"]["voxels_in"] > result["conv"][0]["sparse"]["voxels_in"]
