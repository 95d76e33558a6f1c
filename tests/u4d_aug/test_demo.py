"""The demo's report (u4d_aug/demo.py) from step outputs written by hand: tables, reasons, links, pointers."""

from __future__ import annotations

import json
from pathlib import Path

from u4d_aug.demo import Step, demo_report, full_results


def write_outputs(out: Path) -> None:
    """eval_u4d with FRD and no FPD extractor, no eval_baseline, a downstream results.json of two arms."""
    table1 = {
        "jsd": {"value": 0.321},
        "mmd": {"value": 66.04},
        "frd": {"value": 9347.2},
        "fpd": {"value": None, "missing": "no --extractor-fpd checkpoint given"},
        "points": {"value": 54717.6, "real": 121879.0},
    }
    (out / "eval_u4d").mkdir(parents=True)
    (out / "eval_u4d" / "evaluation.json").write_text(json.dumps({"counts": {"bank": 8, "real": 18}, "table1": table1}))
    arms = [
        {"arm": "sup-only", "status": "done", "miou": {"mean": 0.1027}, "ece_per_scan": {"mean": 0.1809}},
        {"arm": "mt", "status": "done", "miou": {"mean": 0.0881}, "reliability_png": "reliability_mt.png"},
    ]
    contrasts = [{"arm": "mt", "reference": "sup-only", "miou": {"mean": -0.0146}, "ece_per_scan": {}}]
    (out / "downstream").mkdir()
    (out / "downstream" / "results.json").write_text(json.dumps({"arms": arms, "contrasts": contrasts}))
    (out / "downstream" / "reliability_mt.png").write_bytes(b"png")
    (out / "generated.png").write_bytes(b"png")


def test_report_tables_say_what_ran_and_why_a_metric_is_absent(tmp_path):
    write_outputs(tmp_path)
    shipped = {"u4d_stage1": Path("a.pt"), "extractor_frd": Path("f.pt")}  # no FPD extractor shipped
    timings = [(Step("simulate", "simulate a small world", ["simulate"]), 5.25), (Step("x", "downstream", []), 44.8)]
    report = demo_report(tmp_path, timings, shipped)
    lines = report.splitlines()
    u4d = next(line for line in lines if line.startswith("| u4d |"))
    assert "| 8 | 18 | 0.321 | 66.0 | 9347 |" in u4d and "absent: no shipped FPD extractor" in u4d and "54718" in u4d
    assert "| baseline | not run |" in report
    assert "| sup-only | done | 10.27 | 18.09 | - |" in report and "| mt | done | 8.81 | - | - |" in report
    assert "| mt - sup-only | -1.46 | - |" in report
    linked = [line.split("](")[1].rstrip(")") for line in lines if "](" in line]
    assert linked == ["generated.png", "downstream/reliability_mt.png"]  # only figures that exist
    assert "## Wall time of this run (50 s)" in report and "| 2 | downstream | 44.8 |" in report
    # without shipped nets the report says the banks are the seconds-trained nets' and FPD/FRD reasons come from there
    assert "No shipped nets were found" in demo_report(tmp_path, timings, None)


def test_full_results_are_marked_until_they_exist(tmp_path):
    assert full_results(tmp_path).count("(not measured yet)") == 3
    (tmp_path / "benchmarks" / "results" / "downstream").mkdir(parents=True)
    text = full_results(tmp_path)
    assert text.count("(not measured yet)") == 2
    assert text.endswith("downstream `benchmarks/results/downstream/`")
