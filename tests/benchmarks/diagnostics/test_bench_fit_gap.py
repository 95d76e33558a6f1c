"""benchmarks/diagnostics/bench_fit_gap.py: mIoU of a tiny mean-teacher checkpoint on its three scan sets."""

from __future__ import annotations

import json
import math
import sys

import pytest

from segmentation.config import SegTrainConfig
from segmentation.train import train
from tests.tiny_nets import SEG_TINY_SEMI, load_script
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config

bench = load_script("diagnostics/bench_fit_gap")
SETS = {"labelled", "unseen_same_places", "held_out_places"}


@pytest.fixture(scope="module")
def semi_checkpoint(tmp_path_factory: pytest.TempPathFactory):
    """A 3-step tiny mean-teacher run on a toy root of 6 frames per sequence: its last checkpoint."""
    tmp = tmp_path_factory.mktemp("fit_gap")
    root = write_toy_root(tmp / "toy", frames=6)
    overrides = [f"data.root={root}", f"out_dir={tmp / 'run'}", "semi.burn_in_steps=2", "data.max_points=600"]
    train(load_config(SegTrainConfig, SEG_TINY_SEMI, [*overrides, "optim.steps=3"]), progress=False)
    return tmp / "run" / "checkpoints" / "step_0000003.pt"


def test_scores_a_tiny_run_on_its_three_scan_sets(semi_checkpoint, tmp_path, monkeypatch):
    out = tmp_path / "fit_gap.json"
    for weights in ("model", "ema"):
        argv = ["bench_fit_gap.py", str(semi_checkpoint), "--scans", "2", "--weights", weights, "--threads", "1"]
        monkeypatch.setattr(sys, "argv", [*argv, "--out", str(out)])
        assert bench.main() == 0
        result = json.loads(out.read_text())
        assert result["scans"] == 2 and len(result["runs"]) == 1
        run = result["runs"][0]
        assert run["weights"] == weights and run["step"] == 3 and run["mode"] == "semi"
        assert set(run["sets"]) == SETS
        for scores in run["sets"].values():
            assert 1 <= scores["scans"] <= 2
            assert math.isfinite(scores["miou"]) and 0.0 <= scores["miou"] <= 1.0
            assert math.isfinite(scores["ece_per_scan"])


def test_a_missing_weight_set_is_a_one_line_error(tmp_path, monkeypatch, semi_checkpoint, capsys):
    import torch

    state = torch.load(semi_checkpoint, weights_only=True)
    state["ema"] = None
    path = tmp_path / "no_ema.pt"
    torch.save(state, path)
    out = tmp_path / "fit_gap.json"
    monkeypatch.setattr(sys, "argv", ["bench_fit_gap.py", str(path), "--weights", "ema", "--out", str(out)])
    assert bench.main() == 2
    assert "no 'ema' weights" in capsys.readouterr().err and not out.exists()
