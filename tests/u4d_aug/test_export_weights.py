"""`u4d export-weights` (u4d_aug/export_weights.py) on tiny untrained diffusion checkpoints: what the file holds,
where a run folder points, the row mean of the training images, refusals. The format itself and the exported nets'
outputs are tested in test_weights.py."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import pytest
import torch

from tests.tiny_nets import TINY
from tests.tiny_worlds import write_tiny_world
from u4d_aug.batches import row_mean
from u4d_aug.config import load_config
from u4d_aug.errors import InputError
from u4d_aug.export_weights import (
    add_export_weights_arguments,
    checkpoint_file,
    export_weights,
    run_export_weights,
    trained_info,
)
from u4d_aug.io import file_sha256
from u4d_aug.stage import DiffusionTrainConfig
from u4d_aug.weights import DIFFUSION_KIND, WEIGHTS_FORMAT


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(scans root, probabilities root) of 3 random-ray scans (tests/tiny_worlds.py)."""
    base = tmp_path_factory.mktemp("world")
    write_tiny_world(base / "scans", base / "probs")
    return base / "scans", base / "probs"


def test_trained_info_reads_step_minutes_and_the_source_digest(tmp_path):
    source = tmp_path / "ckpt.pt"
    source.write_bytes(b"weights")
    info = trained_info({"step": 40, "elapsed": 90.0}, DIFFUSION_KIND, source)
    assert info == {"step": 40, "elapsed_minutes": 1.5, "source_sha256": file_sha256(source)}
    assert trained_info({"steps": 3, "step": 99}, "frd", source)["step"] == 3  # extractors count `steps`
    assert "elapsed_minutes" not in trained_info({"step": 0}, DIFFUSION_KIND, source)


def test_a_run_folder_stands_for_its_newest_checkpoint(untrained_checkpoints, tmp_path):
    for step in (2, 10):
        path = tmp_path / "run" / "checkpoints" / f"step_{step:07d}.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(untrained_checkpoints["baseline"], path)
    assert checkpoint_file(tmp_path / "run") == tmp_path / "run" / "checkpoints" / "step_0000010.pt"
    assert checkpoint_file(untrained_checkpoints["baseline"]) == untrained_checkpoints["baseline"]
    with pytest.raises(InputError, match="no step_\\*.pt checkpoint in this run folder"):
        checkpoint_file(tmp_path)


@pytest.mark.parametrize(("stage", "key"), [("baseline", "x0"), ("stage1", "x0_u")])
def test_diffusion_weights_are_float16_with_a_stable_hash_and_the_row_mean(
    untrained_checkpoints, world, tmp_path, stage, key
):
    checkpoint = untrained_checkpoints[stage]
    roots = {"data_root": str(world[0]), "probs_root": str(world[1])}
    exported = export_weights(checkpoint, tmp_path / "w.pt", **roots)
    assert exported["kind"] == DIFFUSION_KIND and exported["format"] == WEIGHTS_FORMAT
    assert exported["hash"] == exported["weights_hash"] and len(exported["hash"]) == 16
    assert exported["trained"] == {"step": 0, "elapsed_minutes": 0.0, "source_sha256": file_sha256(checkpoint)}
    assert all(t.dtype == torch.float16 for t in exported["model"].values() if t.is_floating_point())
    assert "ray_features.features" not in exported["model"]  # rebuilt from the config when loaded
    assert torch.load(tmp_path / "w.pt", weights_only=True)["hash"] == exported["hash"]
    assert export_weights(checkpoint, tmp_path / "again.pt", **roots)["hash"] == exported["hash"]
    cfg = load_config(
        DiffusionTrainConfig, TINY, [f"diffusion.stage={stage}", f"data_root={world[0]}", f"probs_root={world[1]}"]
    )
    assert exported["row_mean"]["key"] == key and torch.equal(exported["row_mean"]["mean"], row_mean(cfg, key))
    assert exported["row_mean"]["source"]["data_root"] == str(world[0])


def test_unreadable_training_scans_leave_out_the_row_mean_with_a_warning(untrained_checkpoints, tmp_path, caplog):
    exported = export_weights(untrained_checkpoints["baseline"], tmp_path / "w.pt", data_root=str(tmp_path / "gone"))
    assert "row_mean" not in exported and (tmp_path / "w.pt").is_file()
    assert "no row_mean stored, its training scans cannot be read" in caplog.text


def test_refusals_name_the_file(untrained_checkpoints, tmp_path):
    checkpoint = untrained_checkpoints["stage2"]
    nowhere = str(tmp_path / "nowhere")
    export_weights(checkpoint, tmp_path / "w.pt", data_root=nowhere)
    with pytest.raises(InputError, match="already exported weights; export from the training checkpoint"):
        export_weights(tmp_path / "w.pt", tmp_path / "again.pt")
    with pytest.raises(InputError, match="is a folder; expected a file path to write"):
        export_weights(checkpoint, tmp_path, data_root=nowhere)
    with pytest.raises(InputError, match="would overwrite the training checkpoint itself"):
        export_weights(checkpoint, checkpoint)
    state = torch.load(checkpoint, weights_only=True)
    del state["config"]
    torch.save(state, tmp_path / "no_config.pt")
    with pytest.raises(InputError, match="no_config.pt: u4d-diffusion checkpoint without its resolved config"):
        export_weights(tmp_path / "no_config.pt", tmp_path / "x.pt")


def test_the_command_prints_kind_hash_and_step(untrained_checkpoints, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_export_weights_arguments(parser)
    out = tmp_path / "baseline.pt"
    args = parser.parse_args([str(untrained_checkpoints["baseline"]), "--out", str(out), "--data-root", "nowhere"])
    assert run_export_weights(args) == 0
    printed = capsys.readouterr().out
    digest = torch.load(out, weights_only=True)["hash"]
    assert printed.startswith(f"u4d-diffusion weights: {out} (") and f"hash {digest}, step 0" in printed


def test_weights_that_would_not_load_back_are_refused_and_nothing_is_written(untrained_checkpoints, tmp_path):
    state = torch.load(untrained_checkpoints["baseline"], weights_only=True)
    name = next(iter(state["ema"]["params"]))
    wrong = {**state, "ema": {**state["ema"], "params": {**state["ema"]["params"], name: torch.zeros(3, 5)}}}
    torch.save(wrong, tmp_path / "wrong_shape.pt")
    with pytest.raises(InputError, match=rf"wrong_shape.pt: its exported weights would not load back \(.*{name}"):
        export_weights(tmp_path / "wrong_shape.pt", tmp_path / "out" / "w.pt", data_root="nowhere")
    diverged = {**state, "ema": {**state["ema"], "params": {**state["ema"]["params"]}}}
    diverged["ema"]["params"][name] = torch.full_like(state["ema"]["params"][name], float("nan"))
    torch.save(diverged, tmp_path / "diverged.pt")
    with pytest.raises(InputError, match=rf"diverged.pt: weight {name} has \d+ non-finite values"):
        export_weights(tmp_path / "diverged.pt", tmp_path / "out" / "w.pt", data_root="nowhere")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())  # no file, no temp file
