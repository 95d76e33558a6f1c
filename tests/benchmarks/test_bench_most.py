"""benchmarks/bench_most.py: --quick writes the json (per L: each variant's forward and sample seconds) and .md."""

from __future__ import annotations

import json

from tests.tiny_nets import load_script


def test_quick_run_writes_the_cost_of_each_length(tmp_path):
    out = tmp_path / "most_cost.json"
    assert load_script("bench_most").main(["--quick", "--threads", "1", "--reps", "2", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["benchmark"] == "most_cost" and result["quick"] and (result["height"], result["width"]) == (16, 64)
    assert result["params"]["most"] > result["params"]["plain"] > 0 and "cores" in result["machine"]
    assert sorted(result["frames"]) == ["1", "2", "4"]
    for row in result["frames"].values():
        for variant in ("sequence", "frames", "plain"):
            assert row[variant]["forward_s"] > 0 and row[variant]["sample_s"] > 0
            assert len(row[variant]["forward_s_reps"]) == 2
        assert row["forward_ratio_sequence_vs_frames"] > 0 and row["sample_ratio_sequence_vs_plain"] > 0
    assert "| 4 |" in out.with_suffix(".md").read_text()
