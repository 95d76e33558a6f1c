"""Burn-in sharing (`experiment.burn_in_signature`, `start_from_burn_in`): the optimizer settings fix the first
semi.burn_in_steps steps, so a run whose optim differs gets another signature and is no donor's heir."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from segmentation.config import SegTrainConfig
from segmentation.experiment import burn_in_signature, start_from_burn_in
from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.io import atomic_torch_save, atomic_write_text

TINY_SEMI = REPO / "configs" / "seg" / "tiny_semi.yaml"
BURN_IN = 2
# each changes the optimizer's first steps: the step size, its schedule (warm-up, cosine length), the decay,
# the clipping, the scans per step
OPTIM_CHANGES = [
    "optim.lr=0.02",
    "optim.weight_decay=0.1",
    "optim.betas=[0.8, 0.99]",
    "optim.warmup_steps=1",
    "optim.steps=12",
    "optim.grad_clip=1.0",
    "optim.batch_size=4",
]


def run_config(out: Path, mode: str, *overrides: str) -> SegTrainConfig:
    """configs/seg/tiny_semi.yaml in `mode` with a burn-in of BURN_IN steps, writing to `out`, + overrides."""
    base = [f"mode={mode}", f"out_dir={out}", f"semi.burn_in_steps={BURN_IN}"]
    return load_config(SegTrainConfig, TINY_SEMI, [*base, *overrides])


def write_donor(out: Path, mode: str = "supervised", *overrides: str) -> SegTrainConfig:
    """A finished donor: OUT/burn_in.pt at step BURN_IN (a one-tensor model) and a log of its first steps."""
    donor = run_config(out, mode, *overrides)
    state = {"step": BURN_IN, "model": {"weight": torch.arange(4.0)}, "ema": None, "config": {}}
    atomic_torch_save(out / "burn_in.pt", state)
    atomic_write_text(out / "log.jsonl", "".join(f'{{"step": {s}, "loss": 1.0}}\n' for s in range(1, 5)))
    return donor


@pytest.mark.parametrize("change", OPTIM_CHANGES)
def test_another_optimizer_setting_is_another_burn_in(change, tmp_path):
    supervised = burn_in_signature(run_config(tmp_path / "a", "supervised"))
    assert supervised is not None
    assert burn_in_signature(run_config(tmp_path / "b", "semi")) == supervised  # mode and out_dir apart: the same
    assert burn_in_signature(run_config(tmp_path / "c", "semi", change)) != supervised, change


def test_a_donor_trained_with_another_learning_rate_is_refused(tmp_path):
    donor = write_donor(tmp_path / "donor")
    heir = run_config(tmp_path / "heir", "semi", "optim.lr=0.02")
    assert start_from_burn_in(heir, [donor]) is None
    assert not (tmp_path / "heir").exists()  # nothing written: the run trains its own burn-in

    # control: the same run at the donor's learning rate starts from the donor's step-B checkpoint
    same = run_config(tmp_path / "same", "semi")
    assert start_from_burn_in(same, [donor]) == tmp_path / "donor" / "burn_in.pt"
    started = torch.load(tmp_path / "same" / "checkpoints" / f"step_{BURN_IN:07d}.pt", weights_only=True)
    assert started["step"] == BURN_IN and torch.equal(started["ema"]["weight"], torch.arange(4.0))
    assert started["config"]["optim"]["lr"] == pytest.approx(0.01)
