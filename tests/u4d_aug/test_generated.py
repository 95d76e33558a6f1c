"""GeneratedScans: scans made on the fly from loaded nets, seeded per sample exactly as a `u4d generate` bank."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import u4d_aug.generated
from tests.tiny_nets import PLAIN_SAMPLING, plain_settings, save_random_checkpoint
from tests.tiny_worlds import write_tiny_world
from u4d_aug.bank import BankLayout, read_manifest
from u4d_aug.cli import main
from u4d_aug.config import load_config
from u4d_aug.data.collate import collate_scans
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.generated import GeneratedScans
from u4d_aug.pipeline import generate_u4d, load_generator, to_points
from u4d_aug.sampling_settings import SamplingSettings

DDPM = plain_settings(2, "ddpm")  # these random nets store no training mean


@pytest.fixture(scope="module")
def nets(random_ema_checkpoints) -> dict:
    return {stage: load_generator(path) for stage, path in random_ema_checkpoints.items()}


def scans(stream) -> list[tuple[str, str, np.ndarray]]:
    return [(item["seq"], item["frame"], item["points"]) for item in stream]


def test_the_stream_is_the_bank_of_the_same_settings(random_ema_checkpoints, nets, tmp_path):
    overrides = [
        f"stage1={random_ema_checkpoints['stage1']}",
        f"stage2={random_ema_checkpoints['stage2']}",
        "num=3",
        "batch_size=2",
        "labels=false",  # a bank without the all-ignore label files, as the stream yields labels None
    ]
    sampling = ["steps=2", "sampler=ddpm", *PLAIN_SAMPLING]
    cfg = load_config(GenerateConfig, None, [*overrides, *sampling, "seed=100", "device=cpu"])
    assert cfg.sampling() == DDPM
    generate_bank(cfg, tmp_path / "bank", progress=False)
    bank = ScanDataset(tmp_path / "bank")
    stream = GeneratedScans("u4d", [nets["stage1"], nets["stage2"]], num=3, seed=100, batch_size=2, settings=DDPM)
    made = scans(stream)
    assert len(made) == len(bank) >= 1
    for (seq, frame, points), item in zip(made, bank):
        assert (seq, frame) == (item["seq"], item["frame"])
        np.testing.assert_array_equal(points, item["points"])
        assert item["labels"] is None


def test_same_seed_same_scans_other_seed_other_scans(nets):
    def make(seed: int):
        return scans(GeneratedScans("baseline", [nets["baseline"]], num=2, seed=seed, settings=DDPM))

    a, b, c = make(3), make(3), make(4)
    assert [f for _, f, _ in a] == ["000000", "000001"]
    for (_, _, p), (_, _, q) in zip(a, b):
        np.testing.assert_array_equal(p, q)
    assert not np.array_equal(a[0][2], c[0][2])
    assert a[0][2].dtype == np.float32 and a[0][2].shape[1] == 4


def test_endless_stream_in_a_dataloader(nets):
    stream = GeneratedScans("baseline", [nets["baseline"]], seed=0, batch_size=2, settings=plain_settings(1))
    assert [item["frame"] for item in itertools.islice(stream, 5)] == [f"{i:06d}" for i in range(5)]
    batch = next(iter(DataLoader(stream, batch_size=2, collate_fn=collate_scans)))
    assert batch["labels"] is None and batch["offsets"].shape == (3,) and batch["points"].shape[1] == 4


def test_dataloader_workers_take_every_other_block(nets, monkeypatch):
    monkeypatch.setattr(u4d_aug.generated, "get_worker_info", lambda: SimpleNamespace(id=1, num_workers=2))
    stream = GeneratedScans("baseline", [nets["baseline"]], num=5, seed=0, batch_size=1, settings=plain_settings(1))
    assert [item["frame"] for item in stream] == ["000001", "000003"]


def test_wrong_nets_are_refused(nets):
    with pytest.raises(InputError, match="takes 2"):
        GeneratedScans("u4d", [nets["stage2"]])
    with pytest.raises(InputError, match="not one of"):
        GeneratedScans("complete", [nets["stage2"]])  # type: ignore[arg-type]
    with pytest.raises(InputError, match="expected a stage1"):
        next(iter(GeneratedScans("u4d", [nets["baseline"], nets["stage2"]], num=1, settings=plain_settings(1))))
    with pytest.raises(InputError, match="no stored training mean for stage1.*mean_start_below=None"):
        next(iter(GeneratedScans("u4d", [nets["stage1"], nets["stage2"]], num=1)))  # the default mean start


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict[str, Path]:
    """Random tiny stage 1 and stage 2 exported with the row means of a tiny world (`export-weights --data-root`)."""
    root = tmp_path_factory.mktemp("exported")
    world = (root / "world", root / "probs")
    write_tiny_world(*world, num_scans=2, num_points=3000)
    paths = {}
    for seed, stage in enumerate(("stage1", "stage2")):
        paths[stage] = root / f"{stage}_weights.pt"
        export_weights(save_random_checkpoint(root / f"{stage}.pt", stage, seed), paths[stage], False, *map(str, world))
    return paths


def test_u4d_generate_the_api_and_the_stream_make_the_same_scans_of_one_settings(exported, tmp_path):
    """`u4d generate` with the default sampling keys but the step counts, `generate_u4d` and `GeneratedScans` with
    those settings: the same points, the mean start from the means stored in the weights files included."""
    settings = dataclasses.replace(SamplingSettings(), steps=2, stage1_steps=1)  # dpmpp2m-sde, cap 0.1, mean start
    config = tmp_path / "generate.yaml"
    keys = {"mode": "u4d", **exported, "num": 2, "seed": 5, "batch_size": 1, "device": "cpu"}
    config.write_text("".join(f"{key}: {value}\n" for key, value in keys.items()))
    bank = tmp_path / "bank"
    assert main(["generate", str(config), "--out", str(bank), "steps=2", "stage1_steps=1", "--no-progress"]) == 0
    manifest = read_manifest(bank)
    assert manifest["complete"] and manifest["config"]["mean_start_below"] == settings.mean_start_below
    assert {role: entry["stored_in"] for role, entry in manifest["mean_start"].items()} == {
        role: str(path) for role, path in exported.items()
    }
    layout = BankLayout(bank)
    written = [read_kitti_scan(layout.scan_path(i)) for i in range(2) if not layout.is_empty(i)]
    assert written, "the tiny nets returned no points at all"

    stage1, stage2 = load_generator(exported["stage1"]), load_generator(exported["stage2"])
    made = []
    for i in range(2):  # batch_size 1: one call per sample, seeded seed + i
        x0 = generate_u4d(stage1, stage2, 1, torch.Generator().manual_seed(5 + i), settings)["x0"]
        made += [cloud for cloud in to_points(x0, stage2.config.sensor, stage2.config.row_mode) if len(cloud)]
    assert len(made) == len(written) and all(np.array_equal(a, b) for a, b in zip(made, written))

    stream = [item["points"] for item in GeneratedScans("u4d", [stage1, stage2], num=2, seed=5, settings=settings)]
    assert len(stream) == len(written) and all(np.array_equal(a, b) for a, b in zip(stream, written))
    own = dataclasses.replace(settings, mean_start_below=None)  # the stored means did start the samplers
    without = [item["points"] for item in GeneratedScans("u4d", [stage1, stage2], num=2, seed=5, settings=own)]
    assert not all(len(a) == len(b) and np.array_equal(a, b) for a, b in zip(without, written))
