"""Run records: a finished run outlives its run folder, stale records are ignored, bad files are named."""

from __future__ import annotations

import json
import logging
import shutil

import pytest

from segmentation.experiment import ExperimentConfig, run_config
from segmentation.records import (
    bank_provenance,
    burn_in_digest,
    first_difference,
    read_record,
    recipe,
    record_path,
    write_record,
)
from tests.segmentation.test_experiment import TINY, TINY_SEMI, tiny_experiment
from u4d_aug.bank import write_manifest
from u4d_aug.config import load_config
from u4d_aug.errors import InputError


def test_records_rebuild_the_table_on_a_machine_without_the_run_folders(tmp_path):
    """Train two arms with records_dir, delete every run folder: the report and a new `u4d experiment` train
    nothing and give the same table, curves and reliability; a changed recipe trains again."""
    records = tmp_path / "records"
    run, _ = tiny_experiment(tmp_path, "optim.steps=2, eval_every=2, semi.burn_in_steps=1, data.val_max_scans=2")
    arms = "arms=[{name: sup-only, mode: supervised}, {name: mt, mode: semi}]"
    assert run(arms, "seeds=[0]", f"records_dir={records}", "final_eval=true") == 0
    out = tmp_path / "out"
    first = json.loads((out / "results.json").read_text())
    paths = sorted(p.relative_to(records).as_posix() for p in records.rglob("*.json"))
    assert paths == ["mt/minkunet/seed0.json", "sup-only/minkunet/seed0.json"]
    record = json.loads((records / "mt" / "minkunet" / "seed0.json").read_text())
    assert record["metrics"]["miou"] == first["arms"][1]["runs"][0]["miou"] and record["metrics"]["bins"]
    assert [step for step, _ in record["curves"]["loss"]] == [1.0, 2.0] and record["host"]["cores"] >= 1
    assert record["recipe"]["mode"] == "semi" and "out_dir" not in record["recipe"]
    # mt started from sup-only's burn-in: both records name the same weights, those of sup-only's burn_in.pt
    sup = json.loads((records / "sup-only" / "minkunet" / "seed0.json").read_text())
    donor = out / "runs" / "sup-only" / "minkunet" / "seed0" / "burn_in.pt"
    assert record["burn_in_weights"] == sup["burn_in_weights"] == burn_in_digest(donor)
    assert burn_in_digest(donor) != burn_in_digest(out / "runs" / "sup-only" / "minkunet" / "seed0" / "model.pt")

    shutil.rmtree(out)  # another machine: only the records came along
    assert run(arms, "seeds=[0]", f"records_dir={records}", "final_eval=true", "--report-only") == 0
    again = json.loads((out / "results.json").read_text())
    assert not (out / "runs").exists()
    for a, b in zip(first["arms"], again["arms"], strict=True):
        assert (a["status"], a["miou"], a["ece_per_scan"], a["iou"]) == (
            b["status"],
            b["miou"],
            b["ece_per_scan"],
            b["iou"],
        )
        assert a["runs"][0]["curves"] == b["runs"][0]["curves"]
        assert b["runs"][0]["out_dir"].endswith("seed0.json")
    assert again["arms"][1]["vs_reference"]["miou"] == first["arms"][1]["vs_reference"]["miou"]
    assert (out / "reliability_mt_minkunet.png").is_file() and (out / "learning_curves_minkunet.png").is_file()
    # training mode also counts a recorded run as finished
    assert run(arms, "seeds=[0]", f"records_dir={records}", "final_eval=true") == 0
    assert not (out / "runs").exists()

    # a record of another recipe stands for nothing: that run trains again and its record is replaced
    changed = "arms=[{name: sup-only, mode: supervised, overrides: [optim.lr=0.5]}, {name: mt, mode: semi}]"
    assert run(changed, "seeds=[0]", f"records_dir={records}", "final_eval=true", "--arms", "sup-only") == 0
    assert (out / "runs" / "sup-only" / "minkunet" / "seed0" / "metrics.json").is_file()
    assert not (out / "runs" / "mt").exists()
    new = json.loads((records / "sup-only" / "minkunet" / "seed0.json").read_text())
    assert new["recipe"]["optim"]["lr"] == 0.5


def test_a_stale_record_is_ignored_with_the_key_that_differs(tmp_path, caplog):
    cfg = load_config(ExperimentConfig, TINY, [f"base={TINY_SEMI}", f"out_dir={tmp_path}"])
    run = run_config(cfg, cfg.arms[0], "minkunet", 0)
    path = record_path(tmp_path / "records", "sup-only", "minkunet", 0)
    write_record(path, run, {"miou": 0.5}, {"loss": [[1.0, 2.0]], "val_miou": []})
    assert read_record(path, run)["metrics"] == {"miou": 0.5}
    run.threads, run.out_dir = 7, tmp_path / "elsewhere"  # bookkeeping: still the same run
    assert read_record(path, run) is not None
    run.optim.lr = 0.123
    caplog.set_level(logging.WARNING, logger="segmentation.records")
    assert read_record(path, run) is None
    assert "optim.lr: record " in caplog.text and ", run 0.123" in caplog.text and str(path) in caplog.text
    assert read_record(tmp_path / "none.json", run) is None


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("{not json", "not valid json"),
        ('{"format": 99}', "expected a run record"),
        ('{"format": 1, "recipe": {}, "metrics": [], "curves": {}}', "field 'metrics' must be an object"),
        ('{"format": 1, "recipe": {}, "metrics": {"miou": "x"}, "curves": {}}', "'metrics.miou' must be a number"),
    ],
)
def test_a_broken_record_is_an_error_naming_the_file(tmp_path, content, match):
    cfg = load_config(ExperimentConfig, TINY, [f"base={TINY_SEMI}", f"out_dir={tmp_path}"])
    path = tmp_path / "seed0.json"
    path.write_text(content)
    with pytest.raises(InputError, match=match) as err:
        read_record(path, run_config(cfg, cfg.arms[0], "minkunet", 0))
    assert str(path) in str(err.value)


def test_bank_provenance_names_the_generator_and_digests_the_scans(tmp_path):
    manifest = {
        "mode": "u4d",
        "checkpoints": {"stage1": "5cb3d641e3274e45"},
        "sampling": {"sampler": "dpmpp2m-sde", "steps": 20},
        "samples": [{"index": i, "sha256": f"{i:064x}"} for i in range(3)],
        "complete": True,
    }
    write_manifest(tmp_path / "bank", manifest)
    first = bank_provenance(tmp_path / "bank")
    assert (first["scans"], first["mode"], first["complete"]) == (3, "u4d", True)
    assert first["checkpoints"] == {"stage1": "5cb3d641e3274e45"} and first["sampling"]["steps"] == 20
    manifest["samples"][1]["sha256"] = "f" * 64  # one scan differs: another digest
    write_manifest(tmp_path / "bank", manifest)
    assert bank_provenance(tmp_path / "bank")["content_sha256"] != first["content_sha256"]
    assert bank_provenance(tmp_path / "none") == {
        "path": str(tmp_path / "none"), "complete": False, "scans": 0, "mode": None, "checkpoints": None,
        "sampling": None, "content_sha256": None,
    }  # fmt: skip


def test_first_difference_names_the_key_path():
    assert first_difference({"a": {"b": 1, "c": 2}}, {"a": {"b": 1, "c": 3}}) == "a.c: record 2, run 3"
    assert first_difference({"a": 1}, {"a": 1, "b": 2}) == "b: only in the run"
    assert first_difference({"a": [1, 2]}, {"a": [1, 2]}) is None


def test_the_recipe_leaves_out_bookkeeping_only():
    cfg = load_config(ExperimentConfig, TINY, [f"base={TINY_SEMI}"])
    data = recipe(run_config(cfg, cfg.arms[0], "minkunet", 3))
    assert data["seed"] == 3 and "optim" in data and "semi" in data
    assert not {"out_dir", "threads", "checkpoint_every", "keep_checkpoints", "num_workers"} & set(data)
    assert json.loads(json.dumps(data)) == data  # plain json


def test_a_key_added_later_keeps_older_records_at_its_former_value():
    cfg = load_config(ExperimentConfig, TINY, [f"base={TINY_SEMI}"])
    run = run_config(cfg, cfg.arms[0], "minkunet", 0)
    assert "unlabeled_sequences" not in recipe(run)["data"]  # null: what every run did before the key existed
    run.data.unlabeled_sequences = ["01", "02"]
    assert recipe(run)["data"]["unlabeled_sequences"] == ["01", "02"]  # set: a different recipe


def test_a_bank_arm_with_a_record_is_reported_where_its_bank_is_absent(tmp_path):
    """Banks stay on the machine that wrote them: on another one, a bank arm's records still give its numbers."""
    run, root = tiny_experiment(tmp_path, "optim.steps=2, eval_every=2")
    arms = f"arms=[{{name: mt+u4d, mode: semi, bank: {tmp_path / 'gone'}}}, "
    arms += f"{{name: mt+r2dm, mode: semi, bank: {tmp_path / 'gone2'}}}]"
    overrides = f"overrides=[data.root={root}, optim.steps=2, eval_every=2]"
    cfg = load_config(ExperimentConfig, TINY, [f"base={TINY_SEMI}", overrides, arms, "seeds=[0]"])
    records = tmp_path / "records"
    metrics = {"miou": 0.5, "ece_per_scan": 0.04, "ece_pooled": 0.03, "iou": {"car": 0.7}}
    write_record(
        record_path(records, "mt+u4d", "minkunet", 0), run_config(cfg, cfg.arms[0], "minkunet", 0), metrics, {}
    )
    assert run(arms, "seeds=[0]", f"records_dir={records}", "--report-only") == 0
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    recorded, absent = results["arms"]
    assert recorded["status"] == "done" and recorded["miou"]["mean"] == 0.5 and recorded["runs"][0]["host"]["cores"]
    assert absent["status"] == "missing" and "not found" in absent["reason"] and "miou" not in absent
