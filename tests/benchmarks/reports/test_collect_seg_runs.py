"""benchmarks/reports/collect_seg_runs.py: per-seed figures and mean +- std from seg-train run folders, bad runs in
one line."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.tiny_nets import REPO

SCRIPT = REPO / "benchmarks" / "reports" / "collect_seg_runs.py"


def fake_run(folder: Path, seed: int, miou: float, views4: float | None, real: float | None) -> Path:
    """A run folder as seg-train + seg-eval leave it: log, config, hosts and the saved eval jsons."""
    folder.mkdir()
    log = [{"step": 0, "class_weight": {"car": 1.0}}]  # a record without time, as train.py writes first
    log += [{"step": s, "time": 1.5 * s, "loss": 2.0 - s / 100} for s in (10, 20)]
    log += [{"step": 20, "time": 31.0, "val_miou": miou - 0.01}, {"step": 24, "time": 36.0, "val_miou": miou}]
    (folder / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in log))
    (folder / "config.yaml").write_text(f"seed: {seed}\nthreads: 1\n")
    (folder / "hosts.jsonl").write_text(json.dumps({"cpu": "test", "cores": 2}) + "\n")
    evaluation = {"miou": miou, "ece_per_scan": 0.02, "ece_pooled": 0.01, "iou": {"car": miou, "road": 0.9}}
    (folder / "eval_96.json").write_text(json.dumps(evaluation))
    if views4 is not None:
        (folder / "eval_96_views4.json").write_text(json.dumps({**evaluation, "miou": views4}))
    if real is not None:
        real_eval = {**evaluation, "miou_present": real, "num_scans": 3, "classes_present": ["car", "road"]}
        (folder / "eval_real.json").write_text(json.dumps(real_eval))
    return folder


def collect(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=120)


def test_collects_seeds_into_mean_and_std(tmp_path):
    a = fake_run(tmp_path / "s0", 0, 0.60, 0.62, 0.40)
    b = fake_run(tmp_path / "s1", 1, 0.70, 0.70, None)
    out = tmp_path / "res" / "recipe.json"
    done = collect(str(a), str(b), "--command", "train seed=S", "--out", str(out))
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    assert result["command"] == "train seed=S"
    assert result["miou_96_mean"] == pytest.approx(0.65)
    assert result["miou_96_std"] == pytest.approx(0.0707107, rel=1e-5)  # sample std of 0.60, 0.70
    assert result["miou_96_views4_mean"] == pytest.approx(0.66)
    assert result["real_miou_present_mean"] == pytest.approx(0.40)  # only the run that has it
    assert result["iou_96_mean"] == pytest.approx({"car": 0.65, "road": 0.9})
    first = result["runs"][0]
    assert (first["seed"], first["steps"], first["train_seconds"]) == (0, 24, 36.0)
    assert first["seconds_per_step"] == pytest.approx(1.5)
    assert [p["step"] for p in first["curve"]] == [20, 24] and first["curve"][1]["minutes"] == pytest.approx(0.6)
    assert first["host"] == {"cpu": "test", "cores": 2}
    assert result["runs"][1]["real_semantickitti"] is None
    assert (tmp_path / "res" / "recipe_learning_curve.png").stat().st_size > 0
    assert "65.00 +- 7.07 %" in done.stdout
    assert first["variants"] == ["views4"] and result["runs"][1]["variants"] == ["views4"]
    assert result["iou_96_views4_mean"] == pytest.approx({"car": 0.65, "road": 0.9})


def test_every_saved_evaluation_variant_is_collected(tmp_path):
    a = fake_run(tmp_path / "s0", 0, 0.60, None, None)
    b = fake_run(tmp_path / "s1", 1, 0.70, None, None)
    for folder, value in ((a, 0.64), (b, 0.72)):
        evaluation = {"miou": value, "ece_per_scan": 0.03, "iou": {"car": value, "road": 0.9}}
        (folder / "eval_96_trilinear_views8.json").write_text(json.dumps(evaluation))
    (a / "eval_96_views4.json").write_text(json.dumps({"miou": 0.61, "ece_per_scan": 0.02, "iou": {"car": 0.6}}))
    out = tmp_path / "variants.json"
    done = collect(str(a), str(b), "--command", "c", "--out", str(out))
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    assert result["miou_96_trilinear_views8_mean"] == pytest.approx(0.68)
    assert result["runs"][0]["ece_per_scan_96_trilinear_views8"] == pytest.approx(0.03)
    assert "miou_96_views4_mean" not in result  # one run only: no mean over seeds
    assert result["runs"][0]["miou_96_views4"] == pytest.approx(0.61)
    assert "mean mIoU (trilinear_views8) over 2 runs: 68.00 +- 5.66 %" in done.stdout
    assert result["alone_on_machine"] and all(r["alone_on_machine"] for r in result["runs"])


def test_a_run_that_shared_the_machine_is_recorded(tmp_path):
    a = fake_run(tmp_path / "s0", 0, 0.60, None, None)
    b = fake_run(tmp_path / "s1", 1, 0.70, None, None)
    out = tmp_path / "shared.json"
    done = collect(str(a), str(b), "--command", "c", "--out", str(out), "--shared", str(a))
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    assert [r["alone_on_machine"] for r in result["runs"]] == [False, True] and not result["alone_on_machine"]
    done = collect(str(a), "--command", "c", "--out", str(out), "--shared", str(b))
    assert done.returncode != 0 and "--shared" in done.stderr and "not among the runs" in done.stderr


def test_one_run_has_no_std_and_no_views_mean(tmp_path):
    a = fake_run(tmp_path / "s0", 0, 0.6, None, None)
    done = collect(str(a), "--command", "c", "--out", str(tmp_path / "one.json"))
    assert done.returncode == 0, done.stderr
    result = json.loads((tmp_path / "one.json").read_text())
    assert result["miou_96_std"] is None and "miou_96_views4_mean" not in result


def test_a_run_without_its_evaluation_is_one_line_naming_the_file(tmp_path):
    a = fake_run(tmp_path / "s0", 0, 0.6, None, None)
    (a / "eval_96.json").unlink()
    (tmp_path / "bad").mkdir()
    for run, names in ((a, "eval_96.json"), (tmp_path / "bad", "log.jsonl")):
        done = collect(str(run), "--command", "c", "--out", str(tmp_path / "x.json"))
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1 and names in lines[0] and lines[0].startswith("error: ")
    assert not (tmp_path / "x.json").exists()
