"""Issue 44 item 1: every loader of a checkpoint a user hands us reads it with torch.load(weights_only=True).

A pickle that would run code when loaded runs nothing, a truncated or foreign file is a one-line InputError
naming it, and the checkpoints our own training runs write still load.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from segmentation.config import SegTrainConfig
from segmentation.experiment import start_from_burn_in
from segmentation.predict import load_checkpoint as load_seg_checkpoint
from segmentation.train import train as train_segmentor
from tests.tiny_nets import SEG_TINY, diffusion_config, extractor_config, load_script
from tests.tiny_worlds import write_tiny_root, write_tiny_world, write_toy_root
from u4d_aug.config import load_config
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.io import atomic_torch_save
from u4d_aug.metrics.extractors import load_extractor, train_extractor
from u4d_aug.pipeline import load_generator
from u4d_aug.stage import build_net, checkpoint_state
from u4d_aug.train import train as train_diffusion


class Payload:
    """Unpickled, it calls open(marker, "w"): a file appears if a loader runs what a checkpoint hands it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def write_malicious(path: Path, marker: Path) -> Path:
    """A .pt shaped like a diffusion checkpoint whose 'model' is the payload."""
    torch.save({"kind": "u4d-diffusion", "config": {}, "model": Payload(marker)}, path)
    return path


bench_module = functools.cache(load_script)  # each benchmark script imported once


@pytest.fixture(scope="module")
def roots(tmp_path_factory) -> dict[str, Path]:
    """The tiny data of the training tests: diffusion world (+ probabilities), extractor root, segmentation root."""
    base = tmp_path_factory.mktemp("roots")
    write_tiny_world(base / "world", base / "probs")
    return {
        "world": base / "world",
        "probs": base / "probs",
        "extractor": write_tiny_root(base / "extractor"),
        "seg": write_toy_root(base / "seg"),
    }


def seg_config(roots: dict[str, Path], out: Path, *overrides: str) -> SegTrainConfig:
    return load_config(SegTrainConfig, SEG_TINY, [f"data.root={roots['seg']}", f"out_dir={out}", *overrides])


def loaders(roots: dict[str, Path], tmp_path: Path) -> dict[str, Callable[[Path], object]]:
    """name -> a call that reads the checkpoint at the given path the way the command does."""
    world = (roots["world"], roots["probs"])

    def diffusion_resume(path: Path) -> object:
        return train_diffusion(diffusion_config(world, tmp_path / "resume", "baseline"), resume=path, progress=False)

    def segmentor_resume(path: Path) -> object:
        return train_segmentor(seg_config(roots, tmp_path / "seg_resume"), resume=path, progress=False)

    def burn_in(path: Path) -> object:
        donor = seg_config(roots, tmp_path / "donor", "semi.burn_in_steps=1")
        (tmp_path / "donor").mkdir(parents=True, exist_ok=True)
        (tmp_path / "donor" / "burn_in.pt").write_bytes(path.read_bytes())
        return start_from_burn_in(seg_config(roots, tmp_path / "arm", "semi.burn_in_steps=1"), [donor])

    return {
        "pipeline.load_generator": load_generator,
        "train-diffusion --resume": diffusion_resume,
        "extractors.load_extractor": load_extractor,
        "segmentation.predict.load_checkpoint": load_seg_checkpoint,
        "seg-train --resume": segmentor_resume,
        "experiment burn-in": burn_in,
        "bench_generation.training_budget": bench_module("bench_generation").training_budget,
        "bench_pseudo_labels.teacher_outputs": lambda path: bench_module(
            "diagnostics/bench_pseudo_labels"
        ).teacher_outputs(path, 1, 0),
        "weights.export_weights": lambda path: export_weights(path, tmp_path / "exported.pt"),
    }


LOADERS = [
    "pipeline.load_generator",
    "train-diffusion --resume",
    "extractors.load_extractor",
    "segmentation.predict.load_checkpoint",
    "seg-train --resume",
    "experiment burn-in",
    "bench_generation.training_budget",
    "bench_pseudo_labels.teacher_outputs",
    "weights.export_weights",
]


def test_the_payload_would_run_without_weights_only(tmp_path):
    """Control: a plain torch.load (weights_only=False) of the file creates the marker."""
    marker = tmp_path / "ran"
    path = write_malicious(tmp_path / "evil.pt", marker)
    torch.load(path, weights_only=False)
    assert marker.exists()


def _bad_files(tmp_path: Path, marker: Path) -> dict[str, Path]:
    """A malicious pickle, the first half of a real checkpoint and a text file, each in its own folder."""
    for kind in ("malicious", "truncated", "text"):
        (tmp_path / kind).mkdir()
    cfg = diffusion_config((tmp_path, tmp_path), tmp_path / "unused", "baseline")
    net = build_net(cfg)
    atomic_torch_save(tmp_path / "whole.pt", checkpoint_state(cfg, 1, net, EMA(net)))
    data = (tmp_path / "whole.pt").read_bytes()
    (tmp_path / "truncated" / "step_0000001.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "text" / "model.pt").write_text("step: 1\nmodel: weights\n")
    return {
        "malicious": write_malicious(tmp_path / "malicious" / "model.pt", marker),
        "truncated": tmp_path / "truncated" / "step_0000001.pt",
        "text": tmp_path / "text" / "model.pt",
    }


@pytest.mark.parametrize("loader", LOADERS)
def test_bad_files_are_one_line_input_errors_and_run_nothing(loader, roots, tmp_path):
    marker = tmp_path / "ran"
    for kind, path in _bad_files(tmp_path, marker).items():
        with pytest.raises(InputError) as caught:
            loaders(roots, tmp_path / f"{kind}_work")[loader](path)
        message = str(caught.value)
        assert "\n" not in message, (kind, message)
        named = str(path) if loader != "experiment burn-in" else str(tmp_path / f"{kind}_work" / "donor" / "burn_in.pt")
        assert named in message, (kind, message)
        if kind == "malicious":
            assert "refused" in message and "open" in message, message
        else:
            assert "not a readable" in message, (kind, message)
        assert not marker.exists(), kind


def test_our_own_checkpoints_still_load(roots, tmp_path):
    """Tiny real runs of each kind load through every loader that reads them (weights_only=True)."""
    world = (roots["world"], roots["probs"])
    run = tmp_path / "diffusion"
    train_diffusion(diffusion_config(world, run, "stage1", "steps=2"), progress=False)
    net, cfg = load_generator(run)
    assert cfg.diffusion.stage == "stage1" and net.mask_conv is not None
    assert bench_module("bench_generation").training_budget(run)["steps"] == 2
    record = train_diffusion(diffusion_config(world, run, "stage1", "steps=3"), resume="last", progress=False)
    assert record["step"] == 3
    export_weights(run, tmp_path / "stage1.pt")  # a run folder exports its newest checkpoint
    assert bench_module("bench_generation").training_budget(tmp_path / "stage1.pt")["steps"] == 3

    frd_path, frd_hash = train_extractor("frd", extractor_config(roots["extractor"], tmp_path / "extractor"))
    assert load_extractor(frd_path).hash == frd_hash

    seg = tmp_path / "seg"
    train_segmentor(seg_config(roots, seg, "optim.steps=2", "semi.burn_in_steps=1", "eval_every=2"), progress=False)
    assert load_seg_checkpoint(seg / "model.pt")["step"] == 2
    assert load_seg_checkpoint(seg / "checkpoints" / "step_0000002.pt")["step"] == 2
    resumed = seg_config(roots, seg, "optim.steps=3", "semi.burn_in_steps=1", "eval_every=2")
    with pytest.warns(UserWarning, match="changed config"):
        train_segmentor(resumed, resume="last", progress=False)
    assert load_seg_checkpoint(seg / "model.pt")["step"] == 3
    donor = seg_config(roots, seg, "optim.steps=2", "semi.burn_in_steps=1")
    arm = seg_config(roots, tmp_path / "arm", "optim.steps=2", "semi.burn_in_steps=1")
    assert start_from_burn_in(arm, [donor]) == seg / "burn_in.pt"
    assert (tmp_path / "arm" / "checkpoints" / "step_0000001.pt").is_file()
