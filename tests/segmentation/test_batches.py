"""segmentation.batches: class counts, the order of scans, each step's global batch whatever the ranks, pasting."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from segmentation.batches import TrainBatches, batch_indices, train_class_counts, train_scans
from segmentation.config import SegTrainConfig
from tests.tiny_nets import SEG_TINY
from u4d_aug.config import load_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.distributed import DistInfo
from u4d_aug.errors import InputError


def tiny_config(root: Path, out: Path, *overrides: str) -> SegTrainConfig:
    return load_config(SegTrainConfig, SEG_TINY, [f"data.root={root}", f"out_dir={out}", *overrides])


def test_class_counts_of_the_training_scans(toy_root):
    scans = ScanDataset(toy_root, ["00"], labeled_only=True)
    counts = train_class_counts(scans)
    expected = sum(np.bincount(scans[i]["labels"], minlength=20)[:19] for i in range(len(scans)))
    np.testing.assert_array_equal(counts.numpy(), expected)
    assert counts[0] > 0 and counts[8] > 0 and counts[12] > 0  # car, road, building of the toy scans


def test_batch_indices_are_epochs_of_permutations_and_depend_on_seed_and_step_only():
    order = [i for step in range(6) for i in batch_indices(step, 5, 3, seed=7)]  # 18 draws = 3 epochs + 3
    for epoch in range(3):
        assert sorted(order[5 * epoch : 5 * epoch + 5]) == list(range(5))
    assert batch_indices(4, 5, 3, seed=7) == batch_indices(4, 5, 3, seed=7)
    assert [batch_indices(s, 50, 2, 1) for s in range(5)] != [batch_indices(s, 50, 2, 2) for s in range(5)]


def test_paste_augmentation_adds_labelled_copies_in_the_batch(toy_root, tmp_path):
    base = ["optim.steps=1", "augment.paste_classes=[car]", "augment.paste_copies=2", "data.max_points=null"]
    scans = ScanDataset(toy_root, ["00", "01"], labeled_only=True)
    plain = TrainBatches(scans, tiny_config(toy_root, tmp_path, *base), 0, 1)[0]
    pasted = TrainBatches(scans, tiny_config(toy_root, tmp_path, *base, "augment.paste_prob=1.0"), 0, 1)[0]
    for before, after, labels in zip(plain["labels"], pasted["labels"], pasted["points"]):
        extra = len(after) - len(before)
        assert extra > 0 and extra % 2 == 0 and len(labels) == len(after)
        assert int((after == 0).sum()) == int((before == 0).sum()) + extra  # every pasted point is a car
    with pytest.raises(InputError, match="paste_classes: unknown class names \\['lorry'\\]"):
        tiny_config(toy_root, tmp_path, "augment.paste_classes=[lorry]")  # refused when the config loads


def test_global_batch_does_not_depend_on_the_number_of_ranks(toy_root):
    cfg = tiny_config(toy_root, toy_root / "unused", "optim.batch_size=3", "data.max_points=500")
    scans = train_scans(cfg, DistInfo(0, 1, 0, torch.device("cpu")))
    single = TrainBatches(scans, cfg, 0, 1)[5]
    rank0, rank1 = TrainBatches(scans, cfg, 0, 2)[5], TrainBatches(scans, cfg, 1, 2)[5]
    merged = [rank0["points"][0], rank1["points"][0], rank0["points"][1]]  # slots 0, 1, 2
    assert all(torch.equal(a, b) for a, b in zip(single["points"], merged))
    assert all(p.shape == (500, 4) for p in single["points"])
