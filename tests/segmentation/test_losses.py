"""Segmentation losses (segmentation/losses.py): the Lovász-softmax against its definition and on hard predictions,
cross-entropy with ignored points and class weights, majority labels per voxel."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from segmentation.config import LossConfig
from segmentation.losses import class_weights, lovasz_softmax, segmentation_loss, voxel_targets


def _jaccard_loss(errors_set: np.ndarray, fg: np.ndarray) -> float:
    """Δ_J(M) = |M| / |fg ∪ M| for the mispredicted set M (Berman et al. 2018, Eq. 5)."""
    union = np.logical_or(fg, errors_set).sum()
    return 0.0 if union == 0 else errors_set.sum() / union


def _lovasz_brute(probs: np.ndarray, target: np.ndarray) -> float:
    """Lovász extension in integral form f(m) = ∫_0^1 Δ({i : m_i >= t}) dt per class, mean over present."""
    losses = []
    for c in np.unique(target):
        fg = target == c
        m = np.abs(fg.astype(float) - probs[:, c])
        levels = np.concatenate([[0.0], np.sort(np.unique(m))])
        total = 0.0
        for lo, hi in itertools.pairwise(levels):  # on (lo, hi] the set {m >= t} is {m >= hi}
            total += (hi - lo) * _jaccard_loss(m >= hi, fg)
        losses.append(total)
    return float(np.mean(losses))


def test_lovasz_matches_brute_force_extension():
    rng = np.random.default_rng(1)
    for _ in range(5):
        logits = torch.from_numpy(rng.normal(size=(7, 3)))
        target = torch.from_numpy(rng.integers(0, 3, 7))
        probs = logits.softmax(1)
        got = float(lovasz_softmax(probs, target))
        assert got == pytest.approx(_lovasz_brute(probs.numpy(), target.numpy()), abs=1e-12)


def test_lovasz_on_hard_predictions_is_one_minus_iou_and_ignores():
    target = torch.tensor([0, 0, 0, 1, 1, 2, 2])
    pred = torch.tensor([0, 0, 1, 1, 2, 2, 2])
    probs = torch.nn.functional.one_hot(pred, 3).double()
    # IoU: class 0 = 2/3, class 1 = 1/3, class 2 = 2/3 -> mean Jaccard loss = (1/3 + 2/3 + 1/3) / 3
    assert float(lovasz_softmax(probs, target)) == pytest.approx(4 / 9)
    # a point with the ignore id changes nothing; perfect predictions give 0
    assert float(lovasz_softmax(torch.cat([probs, probs[:1]]), torch.cat([target, torch.tensor([9])]), 9)) == (
        pytest.approx(4 / 9)
    )
    assert float(lovasz_softmax(torch.nn.functional.one_hot(target, 3).double(), target)) == 0.0


def test_segmentation_loss_weights_and_all_ignored():
    logits = torch.randn(10, 4, requires_grad=True)
    target = torch.tensor([0, 1, 2, 3, 4, 4, 0, 1, 2, 3])  # 4 = ignore
    out = segmentation_loss(logits, target, LossConfig(ce_weight=1.0, lovasz_weight=2.0), ignore_index=4)
    ce = torch.nn.functional.cross_entropy(logits, target, ignore_index=4)
    assert float(out["loss_ce"].detach()) == pytest.approx(float(ce.detach()))
    assert float(out["loss"].detach()) == pytest.approx(float((ce + 2 * out["loss_lovasz"]).detach()))
    out["loss"].backward()
    assert logits.grad[4:6].abs().sum() == 0  # ignored points get no gradient
    empty = segmentation_loss(logits, torch.full((10,), 4), LossConfig(), ignore_index=4)
    assert float(empty["loss"].detach()) == 0.0 and empty["loss"].requires_grad


def test_voxel_targets_are_majority_labels_by_hand():
    ignore = 19
    # voxel 0: 2 x class 3 + 1 x class 5; voxel 1: only ignored points; voxel 2: tie 1 / 4 -> lower id;
    # voxel 3: class 7 beats 2 ignored points
    target = torch.tensor([3, 5, 3, ignore, ignore, 4, 1, 7, ignore, ignore])
    inverse = torch.tensor([0, 0, 0, 1, 1, 2, 2, 3, 3, 3])
    assert voxel_targets(target, inverse, 4, ignore).tolist() == [3, ignore, 1, 7]
    # a voxel without any point (not produced by voxelize, but well defined) is ignored; all-ignored input too
    assert voxel_targets(target, inverse, 5, ignore).tolist() == [3, ignore, 1, 7, ignore]
    assert voxel_targets(torch.full((3,), ignore), torch.tensor([0, 1, 1]), 2, ignore).tolist() == [ignore] * 2
    with pytest.raises(ValueError, match="must match"):
        voxel_targets(target, inverse[:-1], 4, ignore)


def test_inverse_sqrt_class_weights_by_hand():
    counts = torch.tensor([64, 16, 0, 4])  # shares 64/84, 16/84, -, 4/84
    share = counts.double() / 84
    raw = share.clamp_min(1e-12).rsqrt()
    scale = (share * raw)[[0, 1, 3]].sum()  # = sum of sqrt(share) over present classes
    weight = class_weights(counts, LossConfig(class_weighting="inverse_sqrt"))
    expected = torch.tensor([raw[0] / scale, raw[1] / scale, 1.0, raw[3] / scale], dtype=torch.float32)
    torch.testing.assert_close(weight, expected)
    assert float((share * weight.double())[[0, 1, 3]].sum()) == pytest.approx(1.0)  # a point weighs 1 on average
    assert float(weight[3] / weight[0]) == pytest.approx(4.0)  # 16x rarer -> 4x the weight
    capped = class_weights(counts, LossConfig(class_weighting="inverse_sqrt", max_class_weight=1.5))
    assert float(capped.max()) == 1.5 and float(capped[0]) == pytest.approx(float(expected[0]))
    assert class_weights(counts, LossConfig()) is None
    with pytest.raises(ValueError, match="class_weighting"):
        LossConfig(class_weighting="inverse")


def test_weighted_cross_entropy_is_torch_weighted_mean():
    logits = torch.randn(12, 3, generator=torch.Generator().manual_seed(1))
    target = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1, 2, 3, 3, 0])  # 3 = ignore
    weight = torch.tensor([0.5, 2.0, 4.0])
    out = segmentation_loss(logits, target, LossConfig(), ignore_index=3, class_weight=weight)
    keep = target != 3
    per_point = torch.nn.functional.cross_entropy(logits[keep], target[keep], reduction="none")
    w = weight[target[keep]]
    assert float(out["loss_ce"]) == pytest.approx(float((w * per_point).sum() / w.sum()), rel=1e-6)


def test_without_the_lovasz_term_the_loss_is_the_weighted_cross_entropy():
    logits = torch.randn(6, 3, generator=torch.Generator().manual_seed(2))
    target = torch.tensor([0, 1, 2, 2, 1, 0])
    out = segmentation_loss(logits, target, LossConfig(ce_weight=0.5, lovasz_weight=0.0), ignore_index=3)
    assert set(out) == {"loss", "loss_ce"}
    ce = torch.nn.functional.cross_entropy(logits, target)
    assert float(out["loss"]) == pytest.approx(0.5 * float(ce)) and float(out["loss_ce"]) == pytest.approx(float(ce))
