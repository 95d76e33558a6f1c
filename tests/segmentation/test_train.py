"""Supervised segmentation training: schedule, data order, a tiny run, exact resume, CLI."""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from segmentation.batches import TrainBatches, train_scans
from segmentation.config import SegTrainConfig
from segmentation.losses import segmentation_loss, voxel_targets
from segmentation.models import build_model
from segmentation.train import add_seg_train_arguments, run_seg_train, supervised_step, train
from tests.tiny_nets import CPU, REPO, SEG_TINY
from u4d_aug.config import load_config
from u4d_aug.data.labels import SEMANTICKITTI_IGNORE
from u4d_aug.errors import InputError
from u4d_aug.io import read_jsonl
from u4d_aug.validate import NonFiniteLossError

TINY = SEG_TINY


def tiny_config(root: Path, out: Path, *overrides: str) -> SegTrainConfig:
    return load_config(SegTrainConfig, TINY, [f"data.root={root}", f"out_dir={out}", *overrides])


# ------------------------------------------------------------------------------------------- schedule, data


def test_budget_annealed_run_reaches_min_lr_when_the_budget_is_gone(toy_root, tmp_path):
    """A budget used up before the first step: that step already runs at min lr, and the run stops after it."""
    cfg = tiny_config(toy_root, tmp_path / "run", "optim.anneal_to=budget", "max_minutes=1e-9", "optim.warmup_steps=0")
    train(cfg, progress=False)
    records = [r for r in read_jsonl(tmp_path / "run" / "log.jsonl") if "loss" in r]
    assert [r["step"] for r in records] == [1]
    assert records[0]["lr"] == pytest.approx(cfg.optim.lr * cfg.optim.min_lr_ratio)


def test_config_rejects_bad_values(tmp_path):
    with pytest.raises(InputError, match="label_fraction"):
        load_config(SegTrainConfig, TINY, ["data.label_fraction=0"])
    with pytest.raises(InputError, match="optim.step"):
        load_config(SegTrainConfig, TINY, ["optim.step=3"])
    with pytest.raises(InputError, match="loss.level=voxel needs model.name=minkunet"):
        load_config(SegTrainConfig, TINY, ["loss.level=voxel", "model.name=spvcnn"])
    with pytest.raises(InputError, match="loss.level"):
        load_config(SegTrainConfig, TINY, ["loss.level=cell"])
    cfg = load_config(SegTrainConfig, TINY, ["data.val_sequences=[8, '09']"])
    assert cfg.data.val_sequences == ["08", "09"]


# --------------------------------------------------------------------------------------------- training


def _final_weights(out: Path) -> dict[str, torch.Tensor]:
    return torch.load(out / "model.pt", weights_only=True)["model"]


def test_tiny_run_writes_outputs_and_learns(toy_root, tmp_path):
    out = tmp_path / "run"
    summary = train(tiny_config(toy_root, out, "optim.steps=12", "eval_every=6"), progress=False)
    for name in (
        "config.yaml",
        "log.jsonl",
        "learning_curve.png",
        "reliability.png",
        "model.pt",
        "metrics.json",
    ):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == [f"step_{s:07d}.pt" for s in (3, 6, 9, 12)]
    records = read_jsonl(out / "log.jsonl")
    train_records = [r for r in records if "loss" in r]
    assert [r["step"] for r in train_records] == list(range(1, 13))
    assert all(np.isfinite(r["loss"]) and r["lr"] > 0 for r in train_records)
    evals = [r for r in records if "val_miou" in r]
    assert [r["step"] for r in evals] == [6, 12]
    assert train_records[-1]["loss"] < train_records[0]["loss"]
    assert summary["num_scans"] == 3 and summary["miou"] == evals[-1]["val_miou"]  # the last evaluation's
    scored = [v for v in summary["iou"].values() if v is not None]  # classes seen in the labels or predictions
    assert summary["miou"] == pytest.approx(np.mean(scored)) and max(scored) > 0
    assert set(summary["classes_present"]) == {"car", "road", "building"}
    ckpt = torch.load(out / "checkpoints" / "step_0000012.pt", weights_only=True)
    assert ckpt["step"] == 12 and ckpt["ema"] is None and ckpt["config"]["optim"]["steps"] == 12
    assert {"model", "optimizer", "scheduler", "rng", "metrics"} <= set(ckpt)
    # a second run into the same folder must not silently mix with the first
    with pytest.raises(InputError, match="--resume"):
        train(tiny_config(toy_root, out), progress=False)


def test_voxel_level_loss_reads_majority_labels_and_learns(toy_root, tmp_path):
    cfg = tiny_config(toy_root, tmp_path / "voxel", "loss.level=voxel", "loss.lovasz_weight=1.0")
    torch.manual_seed(0)
    model = build_model(cfg.model)
    batch = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1)[0]
    losses = supervised_step(model, batch, cfg, torch.device("cpu"))
    # the same losses by hand: voxel logits against the majority label of each voxel
    out = model(batch["points"], voxel_output=True)
    target = voxel_targets(torch.cat(batch["labels"]), out.inverse, len(out.logits), SEMANTICKITTI_IGNORE)
    want = segmentation_loss(out.logits, target, cfg.loss, SEMANTICKITTI_IGNORE)
    for key in ("loss", "loss_ce", "loss_lovasz"):
        assert float(losses[key].detach()) == pytest.approx(float(want[key].detach()), rel=1e-5), key
    assert len(out.logits) < sum(len(p) for p in batch["points"])  # fewer rows than points
    out_dir = tmp_path / "voxel_run"
    train(tiny_config(toy_root, out_dir, "loss.level=voxel", "optim.steps=12", "eval_every=12"), progress=False)
    records = [r for r in read_jsonl(out_dir / "log.jsonl") if "loss" in r]
    assert records[-1]["loss"] < records[0]["loss"]


def test_class_weighted_run_logs_its_weights(toy_root, tmp_path):
    out = tmp_path / "weighted"
    train(tiny_config(toy_root, out, "optim.steps=2", "loss.class_weighting=inverse_sqrt"), progress=False)
    first = read_jsonl(out / "log.jsonl")[0]
    weight = first["class_weight"]
    assert first["step"] == 0 and weight["car"] > weight["road"] > 0  # the toy scans hold 2x road as car
    ckpt = torch.load(out / "checkpoints" / "step_0000002.pt", weights_only=True)
    assert ckpt["class_weight"].tolist() == pytest.approx(list(weight.values()))


def test_label_fraction_trains_on_the_split(toy_root, tmp_path):
    cfg = tiny_config(toy_root, tmp_path / "run", "data.label_fraction=0.5", "optim.steps=1", "eval_every=1")
    train(cfg, progress=False)
    files = list((tmp_path / "run" / "splits").glob("uniform_50pct_seed0_*.json"))
    assert len(files) == 1  # under --out, named by the fraction, seed and a digest of the train set
    assert not (toy_root / "splits").exists()  # nothing written into the data root
    split = json.loads(files[0].read_text())
    assert (
        split["labeled"]
        and split["unlabeled"]
        and not {tuple(x) for x in split["labeled"]} & {tuple(x) for x in split["unlabeled"]}
    )


def test_resume_in_a_fresh_process_is_bit_exact(toy_root, tmp_path):
    """N = 6 steps with a checkpoint at 3; a new process resumes from step 3; final weights are identical."""
    full = tmp_path / "full"
    cfg = tiny_config(toy_root, full, "model.name=spvcnn")  # dropout: the global RNG matters too
    train(cfg, progress=False)

    half = tmp_path / "half"
    half_cfg = tiny_config(toy_root, half, "model.name=spvcnn")
    (half / "checkpoints").mkdir(parents=True)
    # the killed run: only its checkpoint of step 3 (and the log up to there) survived
    (half / "checkpoints" / "step_0000003.pt").write_bytes((full / "checkpoints" / "step_0000003.pt").read_bytes())
    (half / "log.jsonl").write_text((full / "log.jsonl").read_text())
    code = (
        "import sys; from segmentation.train import train; from segmentation.config import SegTrainConfig; "
        "from u4d_aug.config import load_config; "
        "train(load_config(SegTrainConfig, sys.argv[1], sys.argv[2:]), resume='last', progress=False)"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run(
        [sys.executable, "-c", code, str(TINY), *_overrides(half_cfg)],
        check=True,
        cwd=REPO,
        env=env,
        timeout=300,
    )
    a, b = _final_weights(full), _final_weights(half)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    steps = [r["step"] for r in read_jsonl(half / "log.jsonl") if "loss" in r]
    assert steps == list(range(1, 7))  # records after the checkpoint were replaced, not duplicated
    hosts = read_jsonl(half / "hosts.jsonl")  # one machine record per start: here only the resume at step 3
    assert [h["step"] for h in hosts] == [3] and hosts[0]["cores"] >= 1 and hosts[0]["world_size"] == 1
    assert [h["step"] for h in read_jsonl(full / "hosts.jsonl")] == [0]


def as_written_before_the_run_layer(state: dict) -> dict:
    """A seg-train checkpoint in the key layout of the code before `u4d_aug.run` (its kind under "format") with the
    config keys removed since, at their "off" values."""
    old = {key: value for key, value in state.items() if key != "kind"}
    old["format"] = "u4d-seg-checkpoint"
    config = old["config"]
    config["optim"] |= {"restart_step": 0, "restart_lr": None}
    config["loss"]["point_fraction"] = 1.0
    config["semi"] |= {"teacher_views": 1, "burn_in_teacher": "copy"}
    return old


def test_a_checkpoint_written_before_the_run_layer_resumes_exactly_and_exports(toy_root, tmp_path):
    """The old layout ("format", no "kind"; removed keys in its config) resumes a mean-teacher run to the weights of
    an uninterrupted one, without a changed-config warning; its weights export and load as a segmentor's."""
    from segmentation.predict import load_checkpoint
    from tests.tiny_nets import SEG_TINY_SEMI
    from u4d_aug.export_weights import export_weights
    from u4d_aug.weights import SEGMENTATION_KIND

    overrides = [f"data.root={toy_root}", "semi.burn_in_steps=2", "data.max_points=600"]
    full, half = tmp_path / "full", tmp_path / "half"
    train(load_config(SegTrainConfig, SEG_TINY_SEMI, [*overrides, f"out_dir={full}"]), progress=False)
    state = torch.load(full / "checkpoints" / "step_0000003.pt", weights_only=True)
    assert state["kind"] == "u4d-seg-checkpoint" and "format" not in state
    (half / "checkpoints").mkdir(parents=True)
    torch.save(as_written_before_the_run_layer(state), half / "checkpoints" / "step_0000003.pt")
    (half / "log.jsonl").write_text((full / "log.jsonl").read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        train(
            load_config(SegTrainConfig, SEG_TINY_SEMI, [*overrides, f"out_dir={half}"]), resume="last", progress=False
        )
    a, b = (torch.load(run / "model.pt", weights_only=True) for run in (full, half))
    assert all(torch.equal(a["model"][key], b["model"][key]) for key in a["model"])
    old_final = as_written_before_the_run_layer({**a, "optimizer": None})
    torch.save(old_final, tmp_path / "old_model.pt")
    assert load_checkpoint(tmp_path / "old_model.pt")["step"] == 6
    exported = export_weights(half / "checkpoints" / "step_0000003.pt", tmp_path / "exported.pt")
    assert exported["kind"] == SEGMENTATION_KIND and load_checkpoint(tmp_path / "exported.pt")["step"] == 3


def test_a_run_killed_before_its_first_checkpoint_starts_again_from_step_0(toy_root, tmp_path, caplog):
    """Issue 44: config, log, a temp file of a half-written checkpoint and the lock of a dead process are all a
    killed run left; a new run, with or without --resume, takes the folder over and trains from step 0."""
    fresh = tmp_path / "fresh"
    train(tiny_config(toy_root, fresh), progress=False)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for resume in (None, "last"):
        out = tmp_path / f"killed_{resume}"
        (out / "checkpoints").mkdir(parents=True)
        (out / "config.yaml").write_text("mode: supervised\n")
        (out / "log.jsonl").write_text('{"step": 1, "loss": 9.0}\n{"step": 2, "lo')
        (out / "checkpoints" / ".step_0000003.pt.k1ll3d.tmp").write_bytes(b"half a checkpoint")
        holder = {"pid": dead.pid, "host": socket.gethostname(), "start": None, "started": 0}
        (out / ".lock").write_text(json.dumps(holder))
        with caplog.at_level("INFO", logger="u4d_aug"):
            train(tiny_config(toy_root, out), resume=resume, progress=False)
        assert "took over the lock" in caplog.text and "starting it again from step 0" in caplog.text
        steps = [r["step"] for r in read_jsonl(out / "log.jsonl") if "loss" in r]
        assert steps == list(range(1, 7))
        assert not list(out.rglob("*.tmp")) and not (out / ".lock").exists()
        a, b = _final_weights(fresh), _final_weights(out)
        assert all(torch.equal(a[key], b[key]) for key in a)


def test_a_second_run_on_the_folder_is_refused_while_the_first_holds_it(toy_root, tmp_path):
    out = tmp_path / "busy"
    holder = subprocess.Popen(
        [sys.executable, "-c", f"from u4d_aug.runlock import run_lock\nwith run_lock({str(out)!r}): input()"],
        stdin=subprocess.PIPE,
        text=True,
    )
    try:
        for _ in range(600):
            if (out / ".lock").is_file() and (out / ".lock").read_text().strip():
                break
            time.sleep(0.05)
        with pytest.raises(InputError, match=f"in use by another run \\(pid {holder.pid} on host"):
            train(tiny_config(toy_root, out), progress=False)
        assert not (out / "log.jsonl").exists()
    finally:
        holder.communicate("\n", timeout=60)
    assert not (out / ".lock").exists()
    assert train(tiny_config(toy_root, out, "optim.steps=1"), progress=False) is not None  # free again


def test_a_non_finite_loss_stops_the_run_and_keeps_the_last_good_checkpoint(toy_root, tmp_path, monkeypatch):
    import segmentation.train as seg_train

    def nan_from_step_4(model, batch, *args, **kwargs):
        losses = supervised_step(model, batch, *args, **kwargs)
        return {**losses, "loss": losses["loss"] * (float("nan") if batch["step"] >= 3 else 1.0)}

    monkeypatch.setattr(seg_train, "supervised_step", nan_from_step_4)
    out = tmp_path / "nan"
    with pytest.raises(NonFiniteLossError, match="training step 4: the loss is nan"):
        train(tiny_config(toy_root, out), progress=False)
    assert [c.name for c in (out / "checkpoints").glob("step_*.pt")] == ["step_0000003.pt"]
    state = torch.load(out / "checkpoints" / "step_0000003.pt", weights_only=True)
    assert all(torch.isfinite(value).all() for value in state["model"].values())
    assert not (out / "model.pt").exists() and not (out / ".lock").exists()


@pytest.mark.parametrize(
    ("override", "key"),
    [("optim.lr=.inf", "optim.lr"), ("optim.lr=.nan", "optim.lr"), ("optim.grad_clip=-1", "optim.grad_clip"),
     ("data.sector_deg=.nan", "data.sector_deg"), ("loss.ce_weight=.inf", "loss.ce_weight"),
     ("semi.consistency_weight=.nan", "semi.consistency_weight"), ("max_minutes=.inf", "max_minutes")],
)  # fmt: skip
def test_non_finite_or_negative_numbers_are_refused_at_config_time(toy_root, tmp_path, override, key):
    with pytest.raises(InputError, match=re.escape(key)):
        tiny_config(toy_root, tmp_path, override)


def _overrides(cfg: SegTrainConfig) -> list[str]:
    return [f"data.root={cfg.data.root}", f"out_dir={cfg.out_dir}", f"model.name={cfg.model.name}"]


def test_cli_functions(toy_root, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_seg_train_arguments(parser)
    out = tmp_path / "cli"
    args = parser.parse_args(
        [
            str(TINY),
            f"data.root={toy_root}",
            "optim.steps=2",
            "eval_every=2",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert run_seg_train(args) == 0
    assert (out / "model.pt").is_file()
    args = parser.parse_args([str(TINY), f"data.root={toy_root}", "optim.steps=3", "--out", str(out), "--resume"])
    assert args.resume == "last"
    with pytest.warns(UserWarning, match="optim.steps"):
        assert run_seg_train(args) == 0
    assert torch.load(out / "model.pt", weights_only=True)["step"] == 3


@pytest.mark.parametrize("path", sorted((REPO / "configs" / "seg").glob("*.yaml")), ids=lambda p: p.name)
def test_seg_presets_load(path: Path) -> None:
    cfg = load_config(SegTrainConfig, path, [])
    assert cfg.optim.steps >= 1 and cfg.model.voxel_size > 0
    if path.name.startswith("cpu_"):  # CPU presets: the held-out sequences never train
        train, val = cfg.data.train_sequences, cfg.data.val_sequences
        assert isinstance(val, (str, list)) and train != val
        # supervised 30-minute presets stop at their wall-clock budget; the experiment's semi base has none, so
        # that every arm of `u4d experiment` trains the same number of steps
        assert cfg.max_minutes > 0 if cfg.mode == "supervised" else cfg.max_minutes == 0
