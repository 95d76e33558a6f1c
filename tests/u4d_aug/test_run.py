"""u4d_aug.run: one checkpoint format with a kind (older seg-train ones read too), where a run starts, the log rewound
on resume, the host record, checkpoint rotation, the budget clock, warnings for a changed config."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import ClassVar

import pytest
import torch
import yaml
from torch import nn

from tests.tiny_nets import CPU
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_torch_save, read_jsonl
from u4d_aug.run import (
    Clock,
    begin_run,
    checkpoint_kind,
    checkpoint_state,
    newest_checkpoint,
    open_run,
    restore,
    save_checkpoint,
    warn_config_changes,
)


@dataclass
class Optim:
    lr: float = 0.1
    REMOVED_KEYS: ClassVar[dict] = {"restart_step": (0, "changed nothing")}


@dataclass
class TinyConfig:
    seed: int = 3
    steps: int = 4
    out: str = "runs/tiny"
    optim: Optim = field(default_factory=Optim)


def tiny_state(step: int, elapsed: float = 0.0) -> tuple[dict, nn.Module]:
    torch.manual_seed(step)
    model = nn.Linear(3, 2)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    return checkpoint_state("tiny", TinyConfig(), step, elapsed, model, optimizer, ema=None, metrics={"a": 1}), model


def test_checkpoint_kind_reads_the_field_and_the_format_of_older_seg_checkpoints():
    assert checkpoint_kind({"kind": "u4d-diffusion"}) == "u4d-diffusion"
    assert checkpoint_kind({"format": "u4d-seg-checkpoint", "model": {}}) == "u4d-seg-checkpoint"  # before the field
    assert checkpoint_kind({"kind": "u4d-seg-checkpoint", "format": "u4d-weights-v1"}) == "u4d-seg-checkpoint"
    assert checkpoint_kind({"format": "u4d-weights-v1"}) is None and checkpoint_kind({}) is None


def test_checkpoints_rotate_and_a_run_resumes_from_the_newest(tmp_path):
    out = tmp_path / "run"
    for step in (1, 2, 3):
        state, model = tiny_state(step, elapsed=10.0 * step)
        save_checkpoint(out, state, keep=2)
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["step_0000002.pt", "step_0000003.pt"]
    assert newest_checkpoint(out) == out / "checkpoints" / "step_0000003.pt"
    with pytest.raises(InputError, match="no step_\\*.pt checkpoint in this run folder"):
        newest_checkpoint(tmp_path / "empty")
    start = open_run(out, "last", True, "tiny", "u4d tiny")
    assert start.path == out / "checkpoints" / "step_0000003.pt" and (start.step, start.elapsed) == (3, 30.0)
    assert set(start.checkpoint) >= {"kind", "config", "step", "elapsed", "model", "optimizer", "ema", "rng"}
    assert start.checkpoint["config"]["optim"] == {"lr": 0.1} and start.checkpoint["metrics"] == {"a": 1}
    fresh = nn.Linear(3, 2)
    torch.manual_seed(99)
    restore(start, TinyConfig(), fresh, torch.optim.SGD(fresh.parameters(), lr=0.1))
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), model.state_dict().values()))
    assert torch.equal(torch.get_rng_state(), start.checkpoint["rng"]["torch"])
    with pytest.raises(InputError, match="has no EMA / teacher weights"):
        restore(start, TinyConfig(), fresh, torch.optim.SGD(fresh.parameters(), lr=0.1), ema=nn.Linear(3, 2))
    fresh_start = open_run(tmp_path / "fresh", "last", True, "tiny", "u4d tiny")
    assert fresh_start.checkpoint is None and fresh_start.step == 0
    restore(fresh_start, TinyConfig(), fresh, torch.optim.SGD(fresh.parameters(), lr=0.1))  # nothing to load


def test_only_a_training_checkpoint_of_the_loops_kind_resumes(tmp_path):
    state, _ = tiny_state(2)
    atomic_torch_save(tmp_path / "other.pt", {**state, "kind": "u4d-diffusion"})
    with pytest.raises(InputError, match="other.pt: not a u4d tiny checkpoint \\(a u4d-diffusion checkpoint\\)"):
        open_run(tmp_path / "a", tmp_path / "other.pt", True, "tiny", "u4d tiny")
    weights = {key: state[key] for key in ("kind", "config", "step", "model")}  # a final model.pt, exported weights
    atomic_torch_save(tmp_path / "model.pt", weights)
    with pytest.raises(InputError, match="model.pt: holds weights only .*, no optimizer or EMA state"):
        open_run(tmp_path / "b", tmp_path / "model.pt", True, "tiny", "u4d tiny")


def test_begin_run_writes_the_config_rewinds_the_log_and_records_the_host(tmp_path):
    out = tmp_path / "run"
    state, _ = tiny_state(2)
    save_checkpoint(out, state, keep=0)
    (out / "log.jsonl").write_text("".join(f'{{"step": {s}, "loss": 1.0}}\n' for s in (1, 2, 3, 4)))
    begin_run(out, TinyConfig(steps=8), open_run(out, "last", True, "tiny", "u4d tiny"), CPU)
    assert [r["step"] for r in read_jsonl(out / "log.jsonl")] == [1, 2]  # steps 3-4 are run again
    assert yaml.safe_load((out / "config.yaml").read_text())["steps"] == 8
    begin_run(tmp_path / "fresh", TinyConfig(), open_run(tmp_path / "fresh", None, True, "tiny", "u4d tiny"), CPU)
    hosts = read_jsonl(out / "hosts.jsonl") + read_jsonl(tmp_path / "fresh" / "hosts.jsonl")
    assert [(h["step"], h["world_size"]) for h in hosts] == [(2, 1), (0, 1)] and hosts[0]["cores"] >= 1


def test_resuming_with_a_changed_config_warns_but_not_for_a_removed_key_at_its_off_value(tmp_path):
    out = tmp_path / "run"
    state, _ = tiny_state(2)
    state["config"]["optim"]["restart_step"] = 0  # saved before the key was removed, at its "off" value
    save_checkpoint(out, state, keep=0)
    start = open_run(out, "last", True, "tiny", "u4d tiny")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_config_changes(start, TinyConfig(out="elsewhere"), ignore=("out",))  # the same run
    with pytest.warns(UserWarning, match="resuming with a changed config \\(steps: 4 -> 9\\)"):
        warn_config_changes(start, TinyConfig(steps=9))
    state["config"]["optim"]["restart_step"] = 700
    save_checkpoint(out, state, keep=0)
    with pytest.warns(UserWarning, match="optim.restart_step: 700 -> \\(removed\\)"):
        warn_config_changes(open_run(out, "last", True, "tiny", "u4d tiny"), TinyConfig())


def test_the_clock_counts_the_earlier_starts_and_reads_the_budget():
    clock = Clock(max_minutes=0.0, before=120.0)
    elapsed, used = clock.read()
    assert 120.0 <= elapsed < 180.0 and not used and clock.fraction() == 0.0
    assert Clock(max_minutes=1.0, before=60.0).read()[1] and Clock(max_minutes=4.0, before=60.0).fraction() >= 0.25
