"""The augmentation comparison runner: tiny preset, 1 seed, 2 arms + a missing-bank arm, resumable, CLI."""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import yaml

from segmentation.evaluate import evaluate
from segmentation.experiment import (
    ArmConfig,
    ExperimentConfig,
    add_experiment_arguments,
    bank_problem,
    burn_in_signature,
    donors_on_disk,
    mean_std,
    mean_text,
    paired_differences,
    run_config,
    run_experiment,
)
from tests.segmentation.test_semi import write_bank
from tests.tiny_nets import REPO
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config
from u4d_aug.errors import InputError
from u4d_aug.io import read_jsonl

TINY = REPO / "configs" / "experiment" / "tiny.yaml"
TINY_SEMI = REPO / "configs" / "seg" / "tiny_semi.yaml"


def test_mean_std_over_seeds():
    assert mean_std([0.5]) == {"mean": 0.5, "std": 0.0, "n": 1}
    stat = mean_std([0.2, 0.4, None])
    assert stat["n"] == 2 and stat["mean"] == pytest.approx(0.3) and stat["std"] == pytest.approx(0.1414213562)
    assert mean_std([None]) == {"mean": None, "std": None, "n": 0}


def test_mean_text_marks_one_seed_instead_of_a_zero_spread():
    assert mean_text(mean_std([0.2, 0.4]), scale=100) == "30.00 ± 14.14"
    assert mean_text(mean_std([-0.0125]), scale=100, signed=True) == "-1.25 (1 seed)"
    assert mean_text(mean_std([90.0, 150.0]), scale=1 / 60, digits=1, signed=True) == "+2.0 ± 0.7"
    assert mean_text(mean_std([None])) == "n/a" and mean_text(None) == "n/a"


def test_paired_differences_by_seed():
    """Only seeds both arms finished are paired; p is the paired t-test: t = 2 / (1 / sqrt 3), 2 dof -> p = 0.0742."""
    reference = {0: 0.40, 1: 0.50, 2: 0.45, 7: 0.9}
    other = {0: 0.41, 1: 0.52, 2: 0.48, 5: 0.1}
    paired = paired_differences(reference, other)
    assert paired["seeds"] == [0, 1, 2] and paired["per_seed"] == pytest.approx([0.01, 0.02, 0.03])
    assert paired["mean"] == pytest.approx(0.02) and paired["std"] == pytest.approx(0.01) and paired["n"] == 3
    assert paired["above"] == 3 and paired["p"] == pytest.approx(0.07418, abs=1e-4)
    # one pair, or the same difference in every seed: no test
    assert paired_differences({0: 0.4}, {0: 0.3})["p"] is None and paired_differences({0: 0.4}, {0: 0.3})["above"] == 0
    assert paired_differences({0: 0.4, 1: 0.5}, {0: 0.5, 1: 0.6})["p"] is None


def test_config_rejects_duplicate_arms():
    with pytest.raises(InputError, match="distinct"):
        load_config(ExperimentConfig, TINY, ["arms=[{name: a}, {name: a}]"])


@pytest.mark.parametrize("name", ["../../escaped", "a/b", "..", ""])
def test_arm_names_are_plain_names(name, tmp_path):
    with pytest.raises(InputError, match="arm name .* must be a plain name"):
        load_config(ExperimentConfig, TINY, [f"arms=[{{name: '{name}'}}]", f"out_dir={tmp_path}"])
    assert list(tmp_path.iterdir()) == []  # nothing written, inside or outside out_dir


def test_an_arm_asked_for_that_cannot_run_is_an_error(tmp_path):
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    argv = [str(TINY), f"arms=[{{name: u4d, mode: semi, bank: {tmp_path / 'no_bank'}}}]", "--out", str(tmp_path / "o")]
    with pytest.raises(InputError, match="--arms: arm 'u4d' cannot run: bank .*no_bank not found"):
        run_experiment(parser.parse_args([*argv, "--arms", "u4d"]))


def test_a_bank_still_being_generated_cannot_be_used(tmp_path):
    bank = write_bank(tmp_path / "bank")
    arm = ArmConfig("mt+u4d", "semi", bank=bank)
    assert bank_problem(arm) is None  # a bank written by other tools has no manifest
    (bank / "manifest.json").write_text(
        json.dumps({"mode": "u4d", "samples": [{"index": 0}, {"index": 1}], "complete": False})
    )
    assert "incomplete (2 scans so far)" in bank_problem(arm)
    (bank / "manifest.json").write_text(
        json.dumps({"mode": "u4d", "samples": [{"index": 0}, {"index": 1}], "complete": True})
    )
    assert bank_problem(arm) is None


def test_a_ceiling_bank_from_the_experiments_places_is_refused_before_any_run(tmp_path):
    """The split check: a `u4d bank-real` bank of a training or held-out place stops the experiment, naming both;
    one of a place in no split runs."""
    from u4d_aug.real_bank import write_real_bank

    root = write_toy_root(tmp_path / "toy", ("00", "01", "02"), frames=2)
    write_real_bank(root, ["01"], tmp_path / "held_out", None)
    write_real_bank(root, ["02"], tmp_path / "unused", None)
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    base = [str(TINY), f"overrides=[data.root={root}]"]
    out = ["--out", str(tmp_path / "o")]
    arm = f"arms=[{{name: sup-only, mode: supervised}}, {{name: mt+real, mode: semi, bank: {tmp_path / 'held_out'}}}]"
    with pytest.raises(InputError, match=r"held_out: its real scans come from places also in data.val_sequences: 01"):
        run_experiment(parser.parse_args([*base, arm, *out, "--arms", "sup-only"]))
    assert not (tmp_path / "o").exists()
    ok = arm.replace("held_out", "unused")
    assert run_experiment(parser.parse_args([*base, ok, *out, "--report-only"])) == 0


def test_a_run_folder_locked_by_another_process_is_refused(tmp_path):
    """Runs lock their own folder (arm/backbone/seed), not the experiment's: a locked run stops this process."""
    import os
    import socket

    root = write_toy_root(tmp_path / "toy")
    out = tmp_path / "exp"
    run_dir = out / "runs" / "sup-only" / "minkunet" / "seed0"
    run_dir.mkdir(parents=True)
    holder = {"pid": os.getppid(), "host": socket.gethostname(), "start": None}  # alive: the test runner's parent
    (run_dir / ".lock").write_text(json.dumps(holder))
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    argv = [str(TINY), f"overrides=[data.root={root}, optim.steps=1]", "--out", str(out), "--no-progress"]
    with pytest.raises(InputError, match="seed0: in use by another run"):
        run_experiment(parser.parse_args([*argv, "--arms", "sup-only"]))
    assert not (out / ".lock").exists() and not (run_dir / "log.jsonl").exists()


def test_arm_overrides_change_only_their_arm():
    cfg = load_config(
        ExperimentConfig,
        TINY,
        [
            f"base={TINY_SEMI}",
            "overrides=[optim.steps=7]",
            "arms=[{name: mt, mode: semi}, {name: mt-t075, mode: semi, overrides: [semi.pseudo_threshold=0.75]}]",
        ],
    )
    plain, ablation = (run_config(cfg, arm, "spvcnn", 3) for arm in cfg.arms)
    assert ablation.semi.pseudo_threshold == 0.75 and plain.semi.pseudo_threshold == 0.9
    for run in (plain, ablation):  # the experiment's overrides, backbone and seed reach both arms
        assert run.optim.steps == 7 and run.model.name == "spvcnn" and run.seed == 3 and run.mode == "semi"
    assert ablation.out_dir.parts[-3:] == ("mt-t075", "spvcnn", "seed3")
    with pytest.raises(InputError, match="pseudo_treshold"):
        run_config(cfg, ArmConfig("typo", "semi", overrides=["semi.pseudo_treshold=0.75"]), "minkunet", 0)


def test_backbone_overrides_change_only_their_backbone():
    cfg = load_config(
        ExperimentConfig,
        TINY,
        [f"base={TINY_SEMI}", "overrides=[loss.level=voxel]", "backbone_overrides={spvcnn: [loss.level=point]}"],
    )
    arm = cfg.arms[0]
    assert run_config(cfg, arm, "spvcnn", 0).loss.level == "point"
    assert run_config(cfg, arm, "minkunet", 0).loss.level == "voxel"
    with pytest.raises(ValueError, match="'pointnet' is not a backbone"):
        replace(cfg, backbone_overrides={"pointnet": ["loss.level=point"]})
    with pytest.raises(InputError, match="loss.level=voxel needs model.name=minkunet"):
        run_config(replace(cfg, backbone_overrides={}), arm, "spvcnn", 0)


def test_tiny_experiment_with_a_missing_bank_is_resumable(tmp_path):
    root = write_toy_root(tmp_path / "toy")
    out = tmp_path / "exp"
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    arms = (
        "arms=[{name: sup-only, mode: supervised}, {name: mt-lasermix, mode: semi}, "
        f"{{name: mt-lasermix-u4d, mode: semi, bank: {tmp_path / 'no_bank'}}}]"
    )
    argv = [
        str(TINY),
        f"base={TINY_SEMI}",
        f"overrides=[data.root={root}, optim.steps=3, eval_every=3]",
        arms,
        "--out",
        str(out),
        "--no-progress",
    ]
    assert run_experiment(parser.parse_args(argv)) == 0

    results = json.loads((out / "results.json").read_text())
    by_arm = {e["arm"]: e for e in results["arms"]}
    assert list(by_arm) == ["sup-only", "mt-lasermix", "mt-lasermix-u4d"]
    missing = by_arm["mt-lasermix-u4d"]
    assert missing["status"] == "missing" and "not found" in missing["reason"] and "miou" not in missing
    assert not (out / "runs" / "mt-lasermix-u4d").exists()  # never trained, never faked
    for name in ("sup-only", "mt-lasermix"):
        entry = by_arm[name]
        assert entry["status"] == "done" and entry["miou"]["n"] == 1 and entry["miou"]["std"] == 0.0
        run_dir = out / "runs" / name / "minkunet" / "seed0"
        # the table reports the saved model's scores on the validation scans (here all 3 of sequence 01)
        expected = evaluate(run_dir / "model.pt", root, ["01"], device="cpu")
        assert entry["miou"]["mean"] == pytest.approx(expected["miou"], abs=1e-6)
        assert entry["ece_per_scan"]["mean"] == pytest.approx(expected["ece_per_scan"], abs=1e-6)
        assert entry["ece_pooled"]["mean"] == pytest.approx(expected["ece_pooled"], abs=1e-6)
        assert entry["wall_clock_s"]["mean"] > 0 and entry["iou"]["car"]["mean"] == pytest.approx(
            expected["iou"]["car"]
        )
        assert (out / entry["reliability_png"]).is_file()
        assert json.loads((run_dir / "metrics.json").read_text())["step"] == 3
    semi_ckpt = torch.load(out / "runs" / "mt-lasermix" / "minkunet" / "seed0" / "model.pt", weights_only=True)
    sup_ckpt = torch.load(out / "runs" / "sup-only" / "minkunet" / "seed0" / "model.pt", weights_only=True)
    assert semi_ckpt["config"]["mode"] == "semi" and sup_ckpt["config"]["mode"] == "supervised"
    assert semi_ckpt["config"]["optim"]["steps"] == sup_ckpt["config"]["optim"]["steps"] == 3  # same budget
    markdown = (out / "results.md").read_text()
    assert "| mt-lasermix-u4d | minkunet | missing: bank" in markdown and "Per-class IoU" in markdown

    # a second invocation skips the finished runs (their files are not rewritten) and gives the same table
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("model.pt")}
    assert run_experiment(parser.parse_args(argv)) == 0
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    again = json.loads((out / "results.json").read_text())
    assert [e.get("miou") for e in again["arms"]] == [e.get("miou") for e in results["arms"]]

    # an interrupted run (checkpoint, no metrics.json) is resumed, not restarted
    run_dir = out / "runs" / "sup-only" / "minkunet" / "seed0"
    (run_dir / "metrics.json").unlink()
    (run_dir / "model.pt").unlink()
    assert run_experiment(parser.parse_args(argv)) == 0
    assert json.loads((run_dir / "metrics.json").read_text())["step"] == 3
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["step_0000003.pt"]


def test_arms_share_their_burn_in_and_end_as_if_trained_alone(tmp_path, caplog):
    """mt arms start from sup-only's burn_in.pt at step 2 and end with the weights of a run from scratch."""
    caplog.set_level(logging.INFO, logger="segmentation.experiment")
    root = write_toy_root(tmp_path / "toy")
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    arms = "arms=[{name: sup-only, mode: supervised}, {name: mt, mode: semi}, {name: mt-w05, mode: semi, " + (
        "overrides: [semi.mix_weight=0.5]}]"
    )
    common = [f"base={TINY_SEMI}", f"overrides=[data.root={root}, optim.steps=4, eval_every=4, semi.burn_in_steps=2]"]
    shared, alone = tmp_path / "shared", tmp_path / "alone"
    argv = [str(TINY), *common, arms]
    assert run_experiment(parser.parse_args([*argv, "--no-progress", "--out", str(shared)])) == 0
    shared_log = list(caplog.messages)
    assert run_experiment(parser.parse_args([*argv, "share_burn_in=false", "--no-progress", "--out", str(alone)])) == 0

    def run_dir(out: Path, arm: str) -> Path:
        return out / "runs" / arm / "minkunet" / "seed0"

    # every run that trains its burn-in keeps that checkpoint beside its rotated ones; the shared mt run did not
    assert all((run_dir(alone, arm) / "burn_in.pt").is_file() for arm in ("sup-only", "mt", "mt-w05"))
    assert [(run_dir(shared, arm) / "burn_in.pt").is_file() for arm in ("sup-only", "mt", "mt-w05")] == [
        True,
        False,
        False,
    ]
    # the shared mt run resumed at step 2: its log holds sup-only's first two records, then its own
    sup_log = [r for r in read_jsonl(run_dir(shared, "sup-only") / "log.jsonl") if "loss" in r]
    mt_log = [r for r in read_jsonl(run_dir(shared, "mt") / "log.jsonl") if "loss" in r]
    assert mt_log[:2] == sup_log[:2] and [r["step"] for r in mt_log] == [1, 2, 3, 4] and "loss_mt" in mt_log[2]
    for arm in ("mt", "mt-w05"):  # shared or not, the same final teacher
        a = torch.load(run_dir(shared, arm) / "model.pt", weights_only=True)["model"]
        b = torch.load(run_dir(alone, arm) / "model.pt", weights_only=True)["model"]
        for key in a:
            assert torch.equal(a[key], b[key]), (arm, key)
    # both mean-teacher arms (a semi key read after burn-in apart) start from sup-only's burn-in
    started = [line.split(" -> ")[0] for line in shared_log if " -> " in line]
    announced = [line for line in shared_log if "(the same burn-in)" in line]
    assert started == ["sup-only / minkunet / seed 0", "mt / minkunet / seed 0", "mt-w05 / minkunet / seed 0"]
    assert len(announced) == 2 and all(str(run_dir(shared, "sup-only") / "burn_in.pt") in a for a in announced)


def tiny_experiment(tmp_path: Path, overrides: str) -> tuple[Callable[..., int], Path]:
    """`u4d experiment` on the tiny preset and a toy root, writing to tmp_path/out: (run(*args) -> exit code, root)."""
    root = write_toy_root(tmp_path / "toy")
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    common = [str(TINY), f"base={TINY_SEMI}", f"overrides=[data.root={root}, {overrides}]"]
    flags = ["--no-progress", "--out", str(tmp_path / "out")]
    return (lambda *args: run_experiment(parser.parse_args([*common, *args, *flags]))), root


def test_report_only_trains_nothing_and_pairs_the_seeds_both_arms_finished(tmp_path):
    """sup-only has seeds 0 and 1, mt seed 0: --report-only over seeds 0-2 reports both as partial, paired on seed 0."""
    run, root = tiny_experiment(tmp_path, "optim.steps=2, eval_every=2, semi.burn_in_steps=1, data.val_max_scans=2")
    arms = "arms=[{name: sup-only, mode: supervised}, {name: mt, mode: semi}, {name: mt-b, mode: semi}]"
    assert run("arms=[{name: sup-only}]", "seeds=[0, 1]") == 0
    assert run("arms=[{name: mt, mode: semi}]", "seeds=[0]") == 0
    before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "out" / "runs").rglob("*"))
    assert run(arms, "seeds=[0, 1, 2]", "--report-only") == 0
    assert sorted(p.relative_to(tmp_path) for p in (tmp_path / "out" / "runs").rglob("*")) == before  # trained nothing

    results = json.loads((tmp_path / "out" / "results.json").read_text())
    sup, mt, mt_b = results["arms"]
    assert (sup["status"], mt["status"], mt_b["status"]) == ("partial", "partial", "not run")
    assert [r["seed"] for r in sup["runs"]] == [0, 1] and sup["miou"]["n"] == 2 and "vs_reference" not in sup
    paired = mt["vs_reference"]
    assert paired["arm"] == "sup-only" and paired["miou"]["seeds"] == [0] and paired["miou"]["p"] is None
    assert paired["miou"]["per_seed"] == pytest.approx([mt["runs"][0]["miou"] - sup["runs"][0]["miou"]])
    markdown = (tmp_path / "out" / "results.md").read_text()
    assert "| sup-only | minkunet | partial | 0, 1 |" in markdown and "| mt-b | minkunet | not run: " in markdown
    assert f"| mt | minkunet | partial | 0 | {100 * mt['miou']['mean']:.2f} (1 seed) |" in markdown  # no "± 0.00"
    not_run = next(line for line in markdown.splitlines() if line.startswith("| mt-b | minkunet | not run: "))
    assert not_run.endswith("| - | - | - | - | - | - |")  # no seed, no number
    assert "## Paired by seed against sup-only" in markdown and "| mt | minkunet | 1 | " in markdown

    assert "the last periodic evaluation (2 validation scans)" in markdown
    png = tmp_path / "out" / "paired_minkunet.png"
    assert results["paired_png_minkunet"] == png.name and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # final_eval: each finished model.pt on all 3 validation scans, once (eval_full.json), reported instead
    assert run(arms, "seeds=[0, 1, 2]", "final_eval=true", "--report-only") == 0
    full = json.loads((tmp_path / "out" / "results.json").read_text())["arms"][0]["runs"][0]
    run_dir = tmp_path / "out" / "runs" / "sup-only" / "minkunet" / "seed0"
    expected = evaluate(run_dir / "model.pt", root, ["01"], device="cpu")
    assert full["num_scans"] == 3 and full["miou"] == pytest.approx(expected["miou"])
    assert full["ece_per_scan"] == pytest.approx(expected["ece_per_scan"])
    assert full["periodic_miou"] == json.loads((run_dir / "metrics.json").read_text())["miou"] == sup["runs"][0]["miou"]
    assert len(list((tmp_path / "out" / "runs").rglob("eval_full.json"))) == 3  # the finished runs only
    assert "final evaluation of each model.pt on all 3 labelled" in (tmp_path / "out" / "results.md").read_text()

    with pytest.raises(InputError, match="reference_arm 'nope'"):
        load_config(ExperimentConfig, TINY, [arms, "reference_arm=nope"])

    # contrasts: mt - sup-only (as vs_reference), sup-only - mt (negated); mt-b - mt left out (no finished run)
    contrasts = "contrasts=[[mt, sup-only], [sup-only, mt], [mt-b, mt]]"
    assert run(arms, "seeds=[0, 1, 2]", contrasts, "--report-only") == 0
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    row, back = results["contrasts"]
    assert (row["arm"], row["reference"], row["backbone"]) == ("mt", "sup-only", "minkunet")
    assert row["miou"] == results["arms"][1]["vs_reference"]["miou"]
    assert row["ece_per_scan"]["per_seed"] == results["arms"][1]["vs_reference"]["ece_per_scan"]["per_seed"]
    assert (back["arm"], back["reference"]) == ("sup-only", "mt") and back["miou"]["seeds"] == [0]
    assert back["miou"]["per_seed"] == pytest.approx([-d for d in row["miou"]["per_seed"]])
    markdown = (tmp_path / "out" / "results.md").read_text()
    assert "## Contrasts (points)" in markdown and "| mt | sup-only | minkunet | " in markdown
    with pytest.raises(InputError, match=r"contrasts\[1\] names 'nope'"):
        load_config(ExperimentConfig, TINY, [arms, "contrasts=[[mt, sup-only], [mt, nope]]"])
    with pytest.raises(InputError, match=r"contrasts\[0\] must be \[arm, reference\] with two different arms"):
        load_config(ExperimentConfig, TINY, [arms, "contrasts=[[mt, mt]]"])

    # --arms: trains only the named arm (mt-b, seed 0) with the config's arms and contrasts, reports every arm
    before = {p.relative_to(tmp_path) for p in (tmp_path / "out" / "runs").rglob("*") if "mt-b" not in p.parts}
    assert run(arms, "seeds=[0, 1, 2]", contrasts, "--arms", "mt-b") == 0
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert [(a["arm"], a["status"]) for a in results["arms"]] == [
        ("sup-only", "partial"),
        ("mt", "partial"),
        ("mt-b", "done"),
    ]
    after = {p.relative_to(tmp_path) for p in (tmp_path / "out" / "runs").rglob("*") if "mt-b" not in p.parts}
    assert after == before  # the other arms' unfinished seeds were not trained
    assert [c["arm"] for c in results["contrasts"]] == ["mt", "sup-only", "mt-b"]
    with pytest.raises(InputError, match="--arms: 'nope' is not an arm of the experiment"):
        run(arms, "seeds=[0]", "--arms", "nope")

    # an arm's own seeds: mt on seed 0 only is done with its one seed; seeds outside the experiment's run nothing
    fewer = "arms=[{name: sup-only, mode: supervised}, {name: mt, mode: semi, seeds: [0]}, {name: mt-b, seeds: [5]}]"
    before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "out" / "runs").rglob("*"))
    assert run(fewer, "seeds=[0, 1, 2]", "--arms", "mt", "mt-b") == 0
    assert sorted(p.relative_to(tmp_path) for p in (tmp_path / "out" / "runs").rglob("*")) == before  # trained nothing
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    sup, mt, mt_b = results["arms"]
    assert (sup["status"], mt["status"], [r["seed"] for r in mt["runs"]]) == ("partial", "done", [0])
    assert mt_b["status"] == "not run" and mt_b["reason"] == "its seeds [5] are not among the seeds [0, 1, 2]"
    with pytest.raises(InputError, match=r"arm mt: seeds must list at least one seed"):
        load_config(ExperimentConfig, TINY, ["arms=[{name: mt, mode: semi, seeds: []}]"])

    # an arm's own backbones: mt-b only on spvcnn is left out of the minkunet table (no entry, no contrast)
    one = "arms=[{name: sup-only, mode: supervised}, {name: mt, mode: semi}, {name: mt-b, backbones: [spvcnn]}]"
    assert run(one, "seeds=[0, 1, 2]", contrasts, "--report-only") == 0
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert [a["arm"] for a in results["arms"]] == ["sup-only", "mt"]
    assert [c["arm"] for c in results["contrasts"]] == ["mt", "sup-only"]
    assert "mt-b" not in (tmp_path / "out" / "results.md").read_text()
    with pytest.raises(InputError, match=r"arm mt: backbones must name at least one"):
        load_config(ExperimentConfig, TINY, ["arms=[{name: mt, mode: semi, backbones: []}]"])
    with pytest.raises(InputError, match=r"arms\[0\]\.backbones.* got \[.pointnet.\]"):
        load_config(ExperimentConfig, TINY, ["arms=[{name: mt, mode: semi, backbones: [pointnet]}]"])


def test_an_arm_run_by_another_process_donates_its_burn_in(tmp_path):
    """`arms=[mt]` in a second invocation starts from the burn_in.pt of sup-only, trained by the first one."""
    run, _ = tiny_experiment(tmp_path, "optim.steps=4, eval_every=4, semi.burn_in_steps=2")
    assert run("arms=[{name: sup-only, mode: supervised}]") == 0
    assert run("arms=[{name: mt, mode: semi}]") == 0
    runs = tmp_path / "out" / "runs"
    sup_log = [r for r in read_jsonl(runs / "sup-only" / "minkunet" / "seed0" / "log.jsonl") if "loss" in r]
    mt_log = [r for r in read_jsonl(runs / "mt" / "minkunet" / "seed0" / "log.jsonl") if "loss" in r]
    assert mt_log[:2] == sup_log[:2] and "loss_mt" in mt_log[2]
    assert not (runs / "mt" / "minkunet" / "seed0" / "burn_in.pt").is_file()


def test_a_run_saved_before_a_key_was_removed_still_donates_its_burn_in(tmp_path):
    """A donor's config.yaml written before a key was removed: at its "off" value it still donates its burn_in.pt;
    a burn-in trained with a since-removed setting (a warm restart inside it) does not."""
    run, _ = tiny_experiment(tmp_path, "optim.steps=4, eval_every=4, semi.burn_in_steps=2")
    assert run("arms=[{name: sup-only, mode: supervised}]") == 0
    config = tmp_path / "out" / "runs" / "sup-only" / "minkunet" / "seed0" / "config.yaml"
    saved = yaml.safe_load(config.read_text())
    saved["optim"] |= {"restart_step": 0, "restart_lr": None}
    saved["semi"] |= {"teacher_views": 1, "burn_in_teacher": "copy"}
    config.write_text(yaml.safe_dump(saved))
    assert [str(donor.out_dir) for donor in donors_on_disk(tmp_path / "out")] == [str(config.parent)]
    saved["optim"]["restart_step"] = 1
    config.write_text(yaml.safe_dump(saved))
    assert donors_on_disk(tmp_path / "out") == []


@pytest.mark.parametrize("path", sorted((REPO / "configs" / "experiment").glob("*.yaml")), ids=lambda p: p.name)
def test_experiment_configs_expand_into_valid_runs(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # base presets are relative to the checkout
    cfg = load_config(ExperimentConfig, path, [])
    for backbone in ("minkunet", "spvcnn"):  # `backbones=[spvcnn]` is one override away for every config
        runs = {
            arm.name: run_config(cfg, arm, backbone, cfg.seeds[0]) for arm in cfg.arms
        }  # each arm's overrides parse
        assert len({run.out_dir for run in runs.values()}) == len(runs)
        # each semi arm with a copied burn-in teacher takes its first burn_in_steps steps as a supervised arm does
        # (the pairing by seed holds); it starts from that arm's burn_in.pt when the two burn-ins are as long
        supervised = [run for run in runs.values() if run.mode == "supervised"]
        for name, run in runs.items():
            signature = burn_in_signature(run) if run.mode == "semi" else None
            if signature is None:
                continue
            steps = run.semi.burn_in_steps
            partners = {burn_in_signature(replace(r, semi=replace(r.semi, burn_in_steps=steps))) for r in supervised}
            assert signature in partners, f"{name} shares no supervised arm's first steps"
