"""mIoU by distance band: each point counted in the band of its horizontal range, bands summing to the whole."""

from __future__ import annotations

import numpy as np
import pytest

from segmentation.metrics import ConfusionMatrix, DistanceBands, mean_iou


def test_points_fall_in_the_band_of_their_horizontal_range():
    ranges = np.array([1.0, 9.99, 10.0, 25.0, 49.0, 50.0, 80.0])
    points = np.stack([ranges * 0.6, ranges * 0.8, np.full(len(ranges), 30.0)], axis=1)  # z does not count
    target = np.array([0, 0, 1, 1, 2, 2, 2])
    pred = np.array([0, 1, 1, 1, 2, 0, 2])
    bands = DistanceBands(num_classes=3, ignore_index=None)
    bands.update(pred, target, points)
    rows = bands.summary(("a", "b", "c"))
    assert [row["range"] for row in rows] == [[0, 10], [10, 20], [20, 30], [30, 50], [50, None]]
    assert [row["points"] for row in rows] == [2, 1, 1, 1, 2]
    assert rows[0]["miou"] == pytest.approx(0.5 * (1 / 2 + 0))  # a: 1 of 2 right; b: predicted, absent -> IoU 0
    assert rows[1]["miou"] == 1.0 and rows[1]["iou"]["a"] is None  # only class b there, right
    assert rows[4]["iou"]["c"] == pytest.approx(0.5) and rows[4]["iou"]["a"] == 0.0


def test_bands_add_up_to_the_whole_scan():
    rng = np.random.default_rng(0)
    points = rng.uniform(-70, 70, (5000, 4))
    target, pred = rng.integers(0, 5, 5000), rng.integers(0, 5, 5000)
    target[:100] = 5  # ignore id
    bands, whole = DistanceBands(5, ignore_index=5), ConfusionMatrix(5, ignore_index=5)
    bands.update(pred, target, points)
    whole.update(pred, target)
    assert np.array_equal(sum(m.matrix for m in bands.matrices), whole.matrix)
    assert sum(row["points"] for row in bands.summary(tuple("abcde"))) == 4900
    assert mean_iou(whole.matrix) == pytest.approx(mean_iou(sum(m.matrix for m in bands.matrices)))
