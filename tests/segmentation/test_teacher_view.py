"""The teacher's view: kept pseudo-labels per class on hand-made logits, pooled shares over a toy world's scans as the
mean teacher's threshold and its cut/augmentation make them, and a checkpoint saved before a key was removed."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from segmentation.config import SegTrainConfig
from segmentation.mean_teacher import pseudo_labels
from segmentation.teacher_view import kept_class_counts, load_teacher, teacher_logits, teacher_view
from tests.tiny_nets import SEG_TINY
from tests.tiny_worlds import write_toy_root
from u4d_aug.cli import main as u4d_main
from u4d_aug.data.datasets import ScanDataset


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    """A 4-step tiny checkpoint on a toy root (its scans are the unlabelled source)."""
    base = tmp_path_factory.mktemp("teacher_view")
    root = write_toy_root(base / "root", frames=2)
    assert u4d_main(["seg-train", str(SEG_TINY), f"data.root={root}", "optim.steps=4", "eval_every=4",
                     "data.max_points=1500", "--out", str(base / "seg"), "--no-progress", "--quiet"]) == 0  # fmt: skip
    return base / "seg" / "model.pt", root


def test_kept_class_counts_on_hand_made_logits() -> None:
    cfg = SegTrainConfig()  # semi.pseudo_threshold 0.9
    logits = torch.tensor([[10.0, 0, 0], [0, 10.0, 0], [0, 0, 0], [2.0, 0, 0], [0, 9.0, 0]])
    # softmax confidences: ~1, ~1, 1/3, e^2 / (e^2 + 2) = 0.787, ~1 -> kept: class 0 once, class 1 twice
    assert math.exp(2) / (math.exp(2) + 2) < cfg.semi.pseudo_threshold
    assert kept_class_counts(logits, cfg).tolist() == [1, 2, 0]
    cfg.semi.pseudo_threshold = 0.3
    assert kept_class_counts(logits, cfg).tolist() == [3, 2, 0]  # 1/3 and 0.787 pass; argmax of a tie: class 0


def test_teacher_view_pools_the_mean_teachers_labels(teacher) -> None:
    checkpoint, root = teacher
    cfg, model = load_teacher(checkpoint)
    assert not model.training and cfg.data.max_points == 1500
    scans = [item["points"] for item in ScanDataset(root, ["00"])]
    view = teacher_view(model, cfg, scans)
    assert view["scans"] == len(scans) and view["points"] == 1500 * len(scans)  # cut to data.max_points
    # by hand: scan i cut and augmented with a generator seeded i, thresholded by pseudo_labels
    kept = np.zeros(cfg.model.num_classes)
    for i, scan in enumerate(scans):
        logits, keep = teacher_logits(model, torch.from_numpy(scan), cfg, torch.Generator().manual_seed(i))
        assert keep.shape == (1500,)
        labels, _ = pseudo_labels(logits, cfg.semi.pseudo_threshold, cfg.data.label_set.ignore_index)
        kept += np.bincount(labels[labels != cfg.data.label_set.ignore_index].numpy(), minlength=len(kept))
    assert view["kept_share"] == pytest.approx(kept.sum() / view["points"])
    shares = np.array(list(view["class_share"].values()))
    assert shares == pytest.approx(kept / max(kept.sum(), 1))
    assert list(view["class_share"])[:3] == ["car", "bicycle", "motorcycle"] and len(shares) == cfg.model.num_classes
    assert view["building_share"] == view["class_share"]["building"]
    assert teacher_view(model, cfg, list(scans)) == view  # the same scans in the same order: seen alike


def test_a_checkpoint_saved_with_a_removed_key_still_loads(teacher, tmp_path) -> None:
    """The shipped segmentor's config holds optim.restart_lr (removed since, at its off value)."""
    checkpoint, _ = teacher
    ckpt = torch.load(checkpoint, weights_only=False)
    ckpt["config"]["optim"]["restart_lr"] = None
    torch.save(ckpt, tmp_path / "old.pt")
    cfg, _ = load_teacher(tmp_path / "old.pt")
    assert cfg.semi.pseudo_threshold == SegTrainConfig().semi.pseudo_threshold
