"""segmentation.metrics (mIoU as mmdet3d seg_eval, ECE as Calib3D)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from sklearn.metrics import confusion_matrix as sk_confusion_matrix

from segmentation.metrics import (
    CalibrationAccumulator,
    ConfusionMatrix,
    ReliabilityBins,
    confusion_matrix,
    confusion_shares,
    expected_calibration_error,
    iou_per_class,
    mean_iou,
    reliability_bins,
    scan_ece,
    summarize,
    top_confusions,
    top_label,
)

# ----------------------------------------------------------------------------------------------- IoU


def test_miou_hand_computed():
    target = np.array([0, 0, 1, 1, 2, 3])  # 3 = ignore id
    pred = np.array([0, 1, 1, 1, 0, 2])
    cm = confusion_matrix(pred, target, num_classes=3, ignore_index=3)
    np.testing.assert_array_equal(cm, [[1, 1, 0], [0, 2, 0], [1, 0, 0]])
    # IoU_c = TP / (TP + FP + FN): 1/3, 2/3, 0/1
    np.testing.assert_allclose(iou_per_class(cm), [1 / 3, 2 / 3, 0.0])
    assert mean_iou(cm) == pytest.approx(1 / 3)


def test_confusion_shares_and_top_confusions_hand_computed():
    # rows = ground truth: class 0 has 4 points (2 right, 1 as 1, 1 as 2), class 1 3 points, class 2 none
    cm = np.array([[2, 1, 1], [3, 0, 0], [0, 0, 0]])
    np.testing.assert_allclose(confusion_shares(cm), [[0.5, 0.25, 0.25], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert top_confusions(cm) == [[(1, 0.25), (2, 0.25)], [(0, 1.0)], []]  # ties in class order, zeros left out
    assert top_confusions(cm, k=1) == [[(1, 0.25)], [(0, 1.0)], []]
    assert top_confusions(torch.tensor(cm))[1] == [(0, 1.0)]


def test_miou_skips_absent_classes():
    # class 2 never appears in target nor prediction -> nan, left out of the mean
    cm = confusion_matrix(torch.tensor([0, 0, 1, 3]), torch.tensor([0, 1, 1, 3]), num_classes=4)
    iou = iou_per_class(cm)
    assert np.isnan(iou[2])
    np.testing.assert_allclose(iou[[0, 1, 3]], [1 / 2, 1 / 2, 1.0])
    assert mean_iou(cm) == pytest.approx(2 / 3)
    assert math.isnan(mean_iou(np.zeros((3, 3))))


def test_miou_matches_sklearn_on_random_labels(rng):
    num_classes, ignore = 7, 7
    cm_acc = ConfusionMatrix(num_classes, ignore_index=ignore)
    all_pred, all_target = [], []
    for _ in range(5):  # accumulated over a set of scans of different sizes
        n = int(rng.integers(200, 2000))
        target = rng.integers(0, num_classes + 1, n)  # includes the ignore id
        pred = np.where(rng.random(n) < 0.6, target, rng.integers(0, num_classes, n)).clip(0, num_classes - 1)
        cm_acc.update(torch.from_numpy(pred), target)  # torch and numpy inputs mixed on purpose
        all_pred.append(pred)
        all_target.append(target)
    pred, target = np.concatenate(all_pred), np.concatenate(all_target)
    keep = target != ignore
    sk = sk_confusion_matrix(target[keep], pred[keep], labels=np.arange(num_classes))
    np.testing.assert_array_equal(cm_acc.matrix, sk)
    tp = np.diag(sk)
    sk_iou = tp / (sk.sum(0) + sk.sum(1) - tp)
    np.testing.assert_allclose(iou_per_class(cm_acc.matrix), sk_iou)
    assert mean_iou(cm_acc.matrix) == pytest.approx(sk_iou.mean())


def test_confusion_matrix_merge_and_bad_labels():
    a, b = ConfusionMatrix(3), ConfusionMatrix(3)
    a.update([0, 1], [0, 1])
    b.update([2, 2], [1, 2])
    a.merge(b)
    np.testing.assert_array_equal(a.matrix, confusion_matrix([0, 1, 2, 2], [0, 1, 1, 2], 3))
    np.testing.assert_array_equal(ConfusionMatrix(2).matrix, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="labels must be in"):
        confusion_matrix([0, 5], [0, 1], num_classes=3)
    with pytest.raises(ValueError, match="points"):
        confusion_matrix([0, 1, 2], [0, 1], num_classes=3)


# ----------------------------------------------------------------------------------------------- ECE

# two scans, K = 2 classes, ignore id 2; confidences chosen away from the bin edges
SCAN1_PROBS = [[0.95, 0.05], [0.85, 0.15], [0.35, 0.65], [0.45, 0.55]]
SCAN1_TARGET = [0, 1, 1, 0]  # correct, wrong, correct, wrong
SCAN2_PROBS = [[0.92, 0.08], [0.02, 0.98], [0.75, 0.25], [0.5, 0.5]]
SCAN2_TARGET = [0, 1, 1, 2]  # correct, correct, wrong, ignored
# scan 1: one point per bin -> (0.05 + 0.85 + 0.35 + 0.55) / 4
ECE1 = 1.8 / 4
# scan 2: bin (0.9, 1]: acc 1, conf 0.95, 2 points; bin (0.7, 0.8]: acc 0, conf 0.75, 1 point
ECE2 = (2 * 0.05 + 0.75) / 3
# pooled: (0.9, 1] holds 0.95, 0.92, 0.98 all correct -> |3 - 2.85|; others one point each
ECE_POOLED = (0.15 + 0.85 + 0.35 + 0.55 + 0.75) / 7


def test_ece_hand_computed():
    assert scan_ece(np.array(SCAN1_PROBS), np.array(SCAN1_TARGET), ignore_index=2) == pytest.approx(ECE1)
    assert scan_ece(torch.tensor(SCAN2_PROBS), torch.tensor(SCAN2_TARGET), ignore_index=2) == pytest.approx(ECE2)
    acc = CalibrationAccumulator(ignore_index=2)
    acc.update(np.array(SCAN1_PROBS, dtype=np.float16), SCAN1_TARGET)  # float16 as predict.py writes
    acc.update(torch.tensor(SCAN2_PROBS), torch.tensor(SCAN2_TARGET))
    assert acc.scan_eces == pytest.approx([ECE1, ECE2], abs=1e-3)  # float16 rounding
    assert acc.ece_per_scan == pytest.approx((ECE1 + ECE2) / 2, abs=1e-3)
    assert acc.ece_pooled == pytest.approx(ECE_POOLED, abs=1e-3)
    assert acc.pooled.total == 7
    np.testing.assert_array_equal(acc.pooled.count, [0, 0, 0, 0, 0, 1, 1, 1, 1, 3])


def test_ece_matches_calib3d_loop():
    """Our vectorised bins equal a direct transcription of Calib3D's `_calculate_ece` loop."""
    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(3000, 5, generator=gen) * 2
    target = torch.randint(0, 5, (3000,), generator=gen)
    probs = torch.softmax(logits, dim=1)
    confidence, prediction = probs.max(1)
    accuracy = prediction.eq(target)
    boundaries = torch.linspace(0, 1, 11)
    expected = 0.0
    for lower, upper in zip(boundaries[:-1], boundaries[1:]):
        in_bin = confidence.gt(lower.item()) * confidence.le(upper.item())
        if in_bin.float().mean().item() > 0:
            gap = confidence[in_bin].mean() - accuracy[in_bin].float().mean()
            expected += abs(gap.item()) * in_bin.float().mean().item()
    assert scan_ece(probs, target) == pytest.approx(expected, abs=1e-6)


def test_bin_membership_lower_exclusive_upper_inclusive():
    edges = torch.linspace(0, 1, 11)
    conf = torch.stack([edges[3], edges[3] + 1e-6, torch.tensor(1.0), torch.tensor(0.0)])
    bins = reliability_bins(conf, torch.tensor([True, True, False, True]))
    np.testing.assert_array_equal(bins.count, [0, 0, 1, 1, 0, 0, 0, 0, 0, 1])
    assert bins.total == 4  # confidence 0 is in no bin but still counts in N, as in Calib3D
    assert np.isnan(bins.accuracy[0]) and bins.accuracy[9] == 0.0


def test_ece_near_zero_for_calibrated_predictor():
    rng = np.random.default_rng(1)
    n = 200_000
    confidence = rng.uniform(0.05, 1.0, n)
    correct = rng.random(n) < confidence  # correct ~ Bernoulli(conf): perfectly calibrated
    assert expected_calibration_error(confidence, correct) < 0.01
    # through the probability path, several scans: binary probs with p(class 0) = conf in [0.5, 1]
    acc = CalibrationAccumulator(ignore_index=None)
    for _ in range(8):
        conf = rng.uniform(0.5, 1.0, 50_000)
        target = np.where(rng.random(conf.size) < conf, 0, 1)
        acc.update(np.stack([conf, 1 - conf], axis=1), target)
    assert acc.ece_per_scan < 0.01
    assert acc.ece_pooled < 0.01
    # an over-confident predictor (accuracy = conf - 0.1) is off by 0.1
    assert expected_calibration_error(confidence, rng.random(n) < confidence - 0.1) == pytest.approx(0.1, abs=0.01)


def test_top_label_drops_ignored_points():
    conf, correct = top_label(torch.tensor([[0.2, 0.8], [0.9, 0.1], [0.6, 0.4]]), torch.tensor([1, 5, 1]), 5)
    torch.testing.assert_close(conf, torch.tensor([0.8, 0.6]))
    assert correct.tolist() == [True, False]
    with pytest.raises(ValueError, match=r"\(N, K\)"):
        top_label(torch.ones(3, 2), torch.zeros(4))


def test_empty_scan_is_skipped():
    acc = CalibrationAccumulator(ignore_index=2)
    assert math.isnan(acc.update(np.array(SCAN1_PROBS), [2, 2, 2, 2]))
    assert acc.scan_eces == [] and math.isnan(acc.ece_per_scan) and math.isnan(acc.ece_pooled)
    acc.update(np.array(SCAN1_PROBS), SCAN1_TARGET)
    assert acc.ece_per_scan == pytest.approx(ECE1)


def test_bins_add_and_summary():
    acc1, acc2 = CalibrationAccumulator(2), CalibrationAccumulator(2)
    acc1.update(np.array(SCAN1_PROBS), SCAN1_TARGET)
    acc2.update(np.array(SCAN2_PROBS), SCAN2_TARGET)
    acc1.merge(acc2)
    assert acc1.ece_pooled == pytest.approx(ECE_POOLED)
    assert isinstance(acc1.pooled + ReliabilityBins.empty(), ReliabilityBins)
    cm = ConfusionMatrix(2, ignore_index=2)
    cm.update(np.argmax(SCAN1_PROBS, 1), SCAN1_TARGET)
    summary = summarize(cm, acc1, ("a", "b"))
    assert summary["miou"] == pytest.approx(1 / 3)  # IoU a = 1/3, b = 1/3
    assert summary["ece_per_scan"] == pytest.approx((ECE1 + ECE2) / 2)
    assert summary["bins"]["count"][9] == 3 and summary["bins"]["accuracy"][0] is None
    assert summary["confusion"] == cm.matrix.tolist()
