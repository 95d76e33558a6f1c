"""benchmarks/diagnostics/diag_mean_start.py: generation with the mean start on stage 2 only, run in a tmp folder
whose weights/ and configs/u4d/generate_hdl64.yaml are tiny untrained nets, U4D one net for both stages as shipped
(the script reads both by relative path)."""

from __future__ import annotations

import json
import shutil
import sys

import pytest
import torch

import u4d_aug.pipeline as pipeline
from tests.tiny_nets import TINY, load_script, save_checkpoint
from tests.tiny_worlds import write_tiny_world

bench = load_script("diagnostics/diag_mean_start")


@pytest.fixture
def keep_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_stage_two_alone_starts_from_the_mean(untrained_checkpoints, tmp_path, monkeypatch, keep_threads):
    (tmp_path / "weights").mkdir()
    save_checkpoint(tmp_path / "weights" / "u4d.pt", TINY, ("diffusion.stage=u4d",))
    shutil.copy(untrained_checkpoints["baseline"], tmp_path / "weights" / "baseline.pt")
    config = tmp_path / "configs" / "u4d" / "generate_hdl64.yaml"
    config.parent.mkdir(parents=True)
    lines = ["net: weights/u4d.pt", "baseline: weights/baseline.pt"]
    config.write_text("\n".join([*lines, "steps: 2", "device: cpu", "batch_size: 1", ""]))
    write_tiny_world(tmp_path / "world", tmp_path / "probs", num_scans=2)
    calls = []
    original = pipeline.sample_named

    def spy(name, denoise, shape, steps, generator, **kw):
        calls.append((kw.get("cond") is not None, getattr(denoise, "__qualname__", type(denoise).__name__)))
        return original(name, denoise, shape, steps, generator, **kw)

    monkeypatch.setattr(pipeline, "sample_named", spy)  # restored after the test, with the script's own patch
    monkeypatch.chdir(tmp_path)
    argv = ["diag_mean_start.py", "--below", "-10", "--data-root", str(tmp_path / "world"), "--num", "1"]
    monkeypatch.setattr(sys, "argv", [*argv, "--out", str(tmp_path / "bank")])
    assert bench.main() == 0
    manifest = json.loads((tmp_path / "bank" / "manifest.json").read_text())
    assert manifest["mode"] == "u4d" and manifest["seed"] == 5000 and len(manifest["samples"]) == 1
    assert len(list((tmp_path / "bank").glob("sequences/*/velodyne/*.bin"))) == 1
    conditional = [qualname for cond, qualname in calls if cond]
    unconditional = [qualname for cond, qualname in calls if not cond]
    assert conditional and all(q.startswith("mean_start.") for q in conditional)  # stage 2: the mean start
    assert unconditional and not any(q.startswith("mean_start.") for q in unconditional)  # stage 1 as before
