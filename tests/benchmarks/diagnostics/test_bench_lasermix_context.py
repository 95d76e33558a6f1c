"""benchmarks/diagnostics/bench_lasermix_context.py: a tiny checkpoint on labelled scans alone and LaserMix-ed."""

from __future__ import annotations

import json
import math
import sys

import pytest

from segmentation.config import SegTrainConfig
from segmentation.train import train
from tests.tiny_nets import SEG_TINY, load_script
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config

bench = load_script("diagnostics/bench_lasermix_context")


@pytest.fixture(scope="module")
def seg_checkpoint(tmp_path_factory: pytest.TempPathFactory):
    """A 2-step tiny supervised run on a toy root of 6 frames per sequence: its last checkpoint."""
    tmp = tmp_path_factory.mktemp("lasermix")
    root = write_toy_root(tmp / "toy", frames=6)
    overrides = [f"data.root={root}", f"out_dir={tmp / 'run'}", "data.max_points=600", "optim.steps=2"]
    train(load_config(SegTrainConfig, SEG_TINY, [*overrides, "checkpoint_every=2", "eval_every=2"]), progress=False)
    return sorted((tmp / "run" / "checkpoints").glob("step_*.pt"))[-1]


def test_one_pair_alone_and_mixed(seg_checkpoint, tmp_path, monkeypatch):
    out = tmp_path / "lasermix_context.json"
    argv = ["bench_lasermix_context.py", str(seg_checkpoint), "--pairs", "1", "--areas", "2", "3", "--threads", "1"]
    monkeypatch.setattr(sys, "argv", [*argv, "--out", str(out)])
    assert bench.main() == 0
    result = json.loads(out.read_text())
    assert result["checkpoint"] == str(seg_checkpoint) and result["max_points"] == 600
    assert len(result["pitch_range_deg"]) == 2
    assert [row["areas"] for row in result["rows"]] == [None, 2, 3]
    alone = result["rows"][0]
    for row in result["rows"]:
        assert row["points"] > 0 and 0.0 <= row["accuracy"] <= 100.0
        assert math.isfinite(row["ce"]) and row["ce"] >= 0.0 and 0.0 <= row["miou"] <= 100.0
        assert set(row["iou"]) == set(row["class_points"])
        assert row["points"] == alone["points"]  # a mix swaps points between the pair, it keeps them all


def test_too_few_labelled_scans_is_a_one_line_error(seg_checkpoint, tmp_path, monkeypatch, capsys):
    out = tmp_path / "lasermix_context.json"
    monkeypatch.setattr(sys, "argv", ["x", str(seg_checkpoint), "--pairs", "1000", "--out", str(out)])
    assert bench.main() == 2
    assert "labelled training scans" in capsys.readouterr().err and not out.exists()
