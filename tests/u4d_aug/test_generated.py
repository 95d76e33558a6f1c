"""GeneratedScans: scans made on the fly from loaded nets, seeded per sample exactly as a `u4d generate` bank."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np
import pytest
from torch.utils.data import DataLoader

import u4d_aug.generated
from u4d_aug.config import load_config
from u4d_aug.data.collate import collate_scans
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.generated import GeneratedScans
from u4d_aug.pipeline import load_generator


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
    ]
    cfg = load_config(GenerateConfig, None, [*overrides, "steps=2", "sampler=ddpm", "seed=100", "device=cpu"])
    generate_bank(cfg, tmp_path / "bank", progress=False)
    bank = ScanDataset(tmp_path / "bank")
    stream = GeneratedScans("u4d", [nets["stage1"], nets["stage2"]], num=3, steps=2, seed=100, batch_size=2)
    made = scans(stream)
    assert len(made) == len(bank) >= 1
    for (seq, frame, points), item in zip(made, bank):
        assert (seq, frame) == (item["seq"], item["frame"])
        np.testing.assert_array_equal(points, item["points"])
        assert item["labels"] is None


def test_same_seed_same_scans_other_seed_other_scans(nets):
    def make(seed: int):
        return scans(GeneratedScans("baseline", [nets["baseline"]], num=2, steps=2, seed=seed))

    a, b, c = make(3), make(3), make(4)
    assert [f for _, f, _ in a] == ["000000", "000001"]
    for (_, _, p), (_, _, q) in zip(a, b):
        np.testing.assert_array_equal(p, q)
    assert not np.array_equal(a[0][2], c[0][2])
    assert a[0][2].dtype == np.float32 and a[0][2].shape[1] == 4


def test_endless_stream_in_a_dataloader(nets):
    stream = GeneratedScans("baseline", [nets["baseline"]], steps=1, seed=0, batch_size=2)
    assert [item["frame"] for item in itertools.islice(stream, 5)] == [f"{i:06d}" for i in range(5)]
    batch = next(iter(DataLoader(stream, batch_size=2, collate_fn=collate_scans)))
    assert batch["labels"] is None and batch["offsets"].shape == (3,) and batch["points"].shape[1] == 4


def test_dataloader_workers_take_every_other_block(nets, monkeypatch):
    monkeypatch.setattr(u4d_aug.generated, "get_worker_info", lambda: SimpleNamespace(id=1, num_workers=2))
    stream = GeneratedScans("baseline", [nets["baseline"]], num=5, steps=1, seed=0, batch_size=1)
    assert [item["frame"] for item in stream] == ["000001", "000003"]


def test_wrong_nets_are_refused(nets):
    with pytest.raises(InputError, match="takes 2"):
        GeneratedScans("u4d", [nets["stage2"]])
    with pytest.raises(InputError, match="not one of"):
        GeneratedScans("complete", [nets["stage2"]])  # type: ignore[arg-type]
    with pytest.raises(InputError, match="expected a stage1"):
        next(iter(GeneratedScans("u4d", [nets["baseline"], nets["stage2"]], num=1, steps=1)))
