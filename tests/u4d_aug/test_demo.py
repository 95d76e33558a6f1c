"""The demo's report (u4d_aug/demo.py) from step outputs written by hand: tables, reasons, links, pointers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from u4d_aug.demo import Step, demo_report, demo_steps, full_results, sequence_motion, sequence_table


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
    shipped = {"u4d": Path("a.pt"), "extractor_frd": Path("f.pt")}  # no FPD extractor shipped
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
    assert "The 4D step did not run" in report  # no eval_4d written
    # without shipped nets the report says the banks are the seconds-trained nets' and FPD/FRD reasons come from there
    assert "No shipped nets were found" in demo_report(tmp_path, timings, None)


def test_full_results_are_marked_until_they_exist(tmp_path):
    assert full_results(tmp_path).count("(not measured yet)") == 3
    (tmp_path / "benchmarks" / "results" / "downstream").mkdir(parents=True)
    text = full_results(tmp_path)
    assert text.count("(not measured yet)") == 2
    assert text.endswith("downstream `benchmarks/results/downstream/`")


def test_sequence_table_and_steps(tmp_path):
    table2 = {
        "bank": {"ttce_global": {"3": 0.0214, "4": 0.0377}, "ctc": {"1": 0.26, "2": 0.35, "3": 0.47, "4": 0.63}},
        "real": {"ttce_global": {"3": 0.031}, "ctc": {"1": 0.06}},  # k = 4 absent (too few real frames)
    }
    (tmp_path / "eval_4d").mkdir()
    (tmp_path / "eval_4d" / "evaluation.json").write_text(json.dumps({"table2": table2}))
    lines = sequence_table(tmp_path)
    assert "| generated (U4D+MoST, propagated) | 0.021 | 0.038 | 0.260 | 0.350 | 0.470 | 0.630 |" in lines
    assert "| real (sequence 02) | 0.031 | - | 0.060 | - | - | - |" in lines
    # the steps run only with the shipped 4D nets, and generate along the motion file the demo writes
    weights = {"u4d": Path("a.pt"), "baseline": Path("c.pt")}
    keys = [step.key for step in demo_steps(tmp_path, 0, tmp_path / "none", weights)]
    assert "generate-4d" not in keys
    weights |= {"u4d_most_stage1": Path("m1.pt"), "u4d_most_stage2": Path("m2.pt")}
    steps = {step.key: step for step in demo_steps(tmp_path, 0, tmp_path / "none", weights)}
    generate = steps["generate-4d"].command
    assert f"motion_file={tmp_path / 'motion_4d.npy'}" in generate and "stage1=m1.pt" in generate
    assert list(steps).index("evaluate-4d") == list(steps).index("generate-4d") + 2  # show-4d between
    motion = sequence_motion()  # 1.2 m per frame, 3 degrees left per frame
    assert motion.shape == (5, 4) and np.allclose(np.diff(motion[:, 3]), np.deg2rad(3.0))
    assert np.allclose(np.linalg.norm(np.diff(motion[:, :2], axis=0), axis=1), 1.2)


def test_u4d_is_one_net_for_both_stages(tmp_path):
    shipped = {"u4d": Path("u.pt"), "baseline": Path("c.pt")}
    steps = {step.key: step for step in demo_steps(tmp_path, 0, tmp_path / "none", shipped)}
    assert "stage=u4d" in steps["train-u4d"].command and steps["train-u4d"].command[-1] == str(tmp_path / "u4d")
    assert not [key for key in steps if key.startswith("train-stage")]
    generate = steps["generate-u4d"].command
    assert "net=u.pt" in generate and "stage1=" in generate and "stage2=" in generate  # the preset's own cleared
    # without shipped nets: the seconds-trained one net generates, and the ceiling's bank avoids its places
    own = {step.key: step for step in demo_steps(tmp_path, 0, tmp_path / "none", None)}
    assert f"net={tmp_path / 'u4d'}" in own["generate-u4d"].command
    assert own["bank-real"].command.count(str(tmp_path / "u4d")) == 1
