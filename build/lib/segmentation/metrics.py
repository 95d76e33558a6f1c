"""Segmentation metrics: confusion matrix, per-class IoU / mIoU (mmdet3d `seg_eval`) and ECE (Calib3D).

Pure functions on torch tensors (CPU or CUDA); numpy arrays are accepted everywhere and converted with
`torch.as_tensor`. Results that are reported (IoU vectors, matrices, bins) come back as numpy / Python floats.
Conventions: the confusion matrix has rows = ground truth, columns = prediction (scikit-learn's layout);
points whose target is the ignore id are removed before anything is counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

Array = torch.Tensor | np.ndarray


def _as_tensor(x: Array) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))


def _drop_ignored(target: torch.Tensor, ignore_index: int | None) -> torch.Tensor | None:
    """Boolean mask of the points to keep, or None when nothing is dropped."""
    return None if ignore_index is None else target != ignore_index


# ------------------------------------------------------------------------------------------------ IoU


def confusion_matrix(pred: Array, target: Array, num_classes: int, ignore_index: int | None = None) -> np.ndarray:
    """(K, K) counts, rows = target, columns = prediction, ignore-id targets dropped (mmdet3d seg_eval)."""
    return _confusion_matrix_tensor(_as_tensor(pred), _as_tensor(target), num_classes, ignore_index).cpu().numpy()


def _confusion_matrix_tensor(
    pred: torch.Tensor, target: torch.Tensor, num_classes: int, ignore_index: int | None
) -> torch.Tensor:
    pred, target = pred.reshape(-1).long(), target.reshape(-1).long().to(pred.device)
    if pred.shape != target.shape:
        raise ValueError(f"pred has {pred.numel()} points but target has {target.numel()}")
    keep = _drop_ignored(target, ignore_index)
    if keep is not None:
        pred, target = pred[keep], target[keep]
    if target.numel():
        lo = int(torch.minimum(pred.min(), target.min()))
        hi = int(torch.maximum(pred.max(), target.max()))
        if lo < 0 or hi >= num_classes:
            raise ValueError(
                f"labels must be in [0, {num_classes}) or the ignore id {ignore_index}; got values in [{lo}, {hi}]"
            )
    flat = target * num_classes + pred  # (N,) row-major index into the (K, K) matrix
    return torch.bincount(flat, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


class ConfusionMatrix:
    """Confusion matrix accumulated over a set of scans (one matrix for the whole set, as mmdet3d does)."""

    def __init__(self, num_classes: int, ignore_index: int | None = None) -> None:
        self.num_classes = num_classes
        self.ignore_index = ignore_index
        self._matrix: torch.Tensor | None = None  # (K, K) int64 on the device of the first update

    def update(self, pred: Array, target: Array) -> None:
        """Add one scan (or any set of points): pred and target are (N,) train ids."""
        cm = _confusion_matrix_tensor(_as_tensor(pred), _as_tensor(target), self.num_classes, self.ignore_index)
        self._matrix = cm if self._matrix is None else self._matrix + cm.to(self._matrix.device)

    def merge(self, other: ConfusionMatrix) -> None:
        """Add the counts of another accumulator (e.g. gathered from another process)."""
        if other._matrix is not None:
            self.update_matrix(other.matrix)

    def update_matrix(self, matrix: Array) -> None:
        """Add a (K, K) count matrix (e.g. an all-reduced one)."""
        m = _as_tensor(matrix).long()
        self._matrix = m if self._matrix is None else self._matrix + m.to(self._matrix.device)

    @property
    def matrix(self) -> np.ndarray:
        """(K, K) int64 counts, rows = target, columns = prediction."""
        if self._matrix is None:
            return np.zeros((self.num_classes, self.num_classes), dtype=np.int64)
        return self._matrix.cpu().numpy().astype(np.int64)


def iou_per_class(cm: Array) -> np.ndarray:
    """(K,) IoU_c = TP / (TP + FP + FN); nan where the class is absent from both target and prediction."""
    cm = np.asarray(cm.cpu() if isinstance(cm, torch.Tensor) else cm, dtype=np.float64)
    tp = np.diag(cm)
    union = cm.sum(0) + cm.sum(1) - tp  # TP + FP + FN
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, tp / np.where(union > 0, union, 1.0), np.nan)


def mean_iou(cm: Array) -> float:
    """mIoU = nan-mean of per-class IoU over the classes present (union > 0), as mmdet3d seg_eval."""
    iou = iou_per_class(cm)
    if np.isnan(iou).all():
        return math.nan
    return float(np.nanmean(iou))


def confusion_shares(cm: Array) -> np.ndarray:
    """(K, K) row-normalised confusion: share of class r's ground-truth points predicted as c (0 where r is absent)."""
    cm = np.asarray(cm.cpu() if isinstance(cm, torch.Tensor) else cm, dtype=np.float64)
    totals = cm.sum(axis=1, keepdims=True)
    return np.divide(cm, totals, out=np.zeros_like(cm), where=totals > 0)


def top_confusions(cm: Array, k: int = 2) -> list[list[tuple[int, float]]]:
    """Per ground-truth class, the k other classes its points are most often predicted as, with those shares
    (largest first; classes with a zero share left out)."""
    shares = confusion_shares(cm)
    np.fill_diagonal(shares, 0.0)
    out = []
    for row in shares:
        order = np.argsort(-row, kind="stable")[:k]
        out.append([(int(c), float(row[c])) for c in order if row[c] > 0])
    return out


# ------------------------------------------------------------------------------------------------ ECE


def top_label(probs: Array, target: Array, ignore_index: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Top-label confidence (max prob) and correctness (argmax == target) of non-ignored points (Calib3D)."""
    probs, target = _as_tensor(probs), _as_tensor(target).reshape(-1)
    if probs.ndim != 2 or probs.shape[0] != target.shape[0]:
        raise ValueError(f"probs must be (N, K) with N = {target.shape[0]} targets; got {tuple(probs.shape)}")
    if not probs.is_floating_point() or probs.dtype in (torch.float16, torch.bfloat16):
        probs = probs.float()  # float16 .npy files from predict.py
    target = target.to(probs.device)
    keep = _drop_ignored(target, ignore_index)
    if keep is not None:
        probs, target = probs[keep], target[keep]
    confidence, prediction = probs.max(dim=1)  # (M,), (M,)
    return confidence, prediction == target.long()


@dataclass
class ReliabilityBins:
    """Per-bin counts, confidence sums and correct counts of M equal-width bins on [0, 1] (Calib3D binning).

    Bin m holds the points with lower_m < confidence <= upper_m; `total` counts every valid point (also one
    that falls in no bin, e.g. confidence exactly 0), the denominator Calib3D uses for |B_m| / N.
    Bins add up (`a + b`), so pooled statistics over a whole set never need the points themselves.
    """

    count: np.ndarray  # (M,) int64
    confidence_sum: np.ndarray  # (M,) float64
    correct_sum: np.ndarray  # (M,) float64
    total: int

    @property
    def num_bins(self) -> int:
        return len(self.count)

    @property
    def edges(self) -> np.ndarray:
        """(M + 1,) bin boundaries: torch.linspace(0, 1, M + 1) in float32, as Calib3D."""
        return torch.linspace(0, 1, self.num_bins + 1).double().numpy()

    @property
    def confidence(self) -> np.ndarray:
        """(M,) mean confidence per bin, nan for an empty bin."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.count > 0, self.confidence_sum / np.maximum(self.count, 1), np.nan)

    @property
    def accuracy(self) -> np.ndarray:
        """(M,) accuracy per bin, nan for an empty bin."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.count > 0, self.correct_sum / np.maximum(self.count, 1), np.nan)

    @property
    def ece(self) -> float:
        """ECE = sum_m |B_m| / N * |acc(B_m) - conf(B_m)| (Guo et al. 2017 / Calib3D); nan when N = 0."""
        if self.total == 0:
            return math.nan
        return float(np.abs(self.correct_sum - self.confidence_sum).sum() / self.total)

    def __add__(self, other: ReliabilityBins) -> ReliabilityBins:
        if other.num_bins != self.num_bins:
            raise ValueError(f"cannot add {self.num_bins} bins to {other.num_bins} bins")
        return ReliabilityBins(
            self.count + other.count,
            self.confidence_sum + other.confidence_sum,
            self.correct_sum + other.correct_sum,
            self.total + other.total,
        )

    @classmethod
    def empty(cls, num_bins: int = 10) -> ReliabilityBins:
        return cls(np.zeros(num_bins, np.int64), np.zeros(num_bins), np.zeros(num_bins), 0)

    def to_dict(self) -> dict:
        """Json-ready per-bin table (for results.json and the reliability diagram)."""
        return {
            "edges": self.edges.tolist(),
            "count": self.count.tolist(),
            "confidence": [None if math.isnan(v) else float(v) for v in self.confidence],
            "accuracy": [None if math.isnan(v) else float(v) for v in self.accuracy],
            "total": int(self.total),
            "ece": None if math.isnan(self.ece) else self.ece,
        }


def reliability_bins(confidence: Array, correct: Array, num_bins: int = 10) -> ReliabilityBins:
    """Bin confidences into M equal-width bins, lower < conf <= upper (Calib3D `_calculate_ece`)."""
    confidence = _as_tensor(confidence).reshape(-1)
    if not confidence.is_floating_point() or confidence.dtype in (torch.float16, torch.bfloat16):
        confidence = confidence.float()
    correct = _as_tensor(correct).reshape(-1).to(confidence.device)
    if correct.shape != confidence.shape:
        raise ValueError(f"confidence has {confidence.numel()} points but correct has {correct.numel()}")
    # Calib3D compares with float32 linspace boundaries; bucketize(right=False): upper[i-1] < c <= upper[i]
    upper = torch.linspace(0, 1, num_bins + 1, device=confidence.device)[1:].to(confidence.dtype)
    index = torch.bucketize(confidence, upper)  # (N,) in 0..M, M = above 1
    in_bin = (confidence > 0) & (index < num_bins)
    index = index[in_bin]
    count = torch.bincount(index, minlength=num_bins)
    confidence_sum = torch.bincount(index, weights=confidence[in_bin].double(), minlength=num_bins)
    correct_sum = torch.bincount(index, weights=correct[in_bin].double(), minlength=num_bins)
    return ReliabilityBins(
        count.cpu().numpy().astype(np.int64),
        confidence_sum.cpu().numpy(),
        correct_sum.cpu().numpy(),
        int(confidence.numel()),
    )


def expected_calibration_error(confidence: Array, correct: Array, num_bins: int = 10) -> float:
    """ECE of one set of points (top-label, M equal-width bins) as Calib3D `_calculate_ece`; nan if empty."""
    return reliability_bins(confidence, correct, num_bins).ece


def scan_ece(probs: Array, target: Array, ignore_index: int | None = None, num_bins: int = 10) -> float:
    """Calib3D `calculate_ece` of one scan: probs (N, K), target (N,), ignore id dropped; nan if none left."""
    confidence, correct = top_label(probs, target, ignore_index)
    return expected_calibration_error(confidence, correct, num_bins)


class CalibrationAccumulator:
    """ECE over a set of scans, both ways: per scan then unweighted mean (Calib3D ECEMetric) and pooled.

    Keeps one float per scan and the pooled per-bin sums, never the points. A scan with no valid point is
    skipped (Calib3D would count it as ECE 0, which only dilutes the mean).
    """

    def __init__(self, ignore_index: int | None = None, num_bins: int = 10) -> None:
        self.ignore_index = ignore_index
        self.num_bins = num_bins
        self.scan_eces: list[float] = []
        self.pooled = ReliabilityBins.empty(num_bins)

    def update(self, probs: Array, target: Array) -> float:
        """Add one scan: probs (N, K) softmax, target (N,) train ids. Returns that scan's ECE."""
        confidence, correct = top_label(probs, target, self.ignore_index)
        bins = reliability_bins(confidence, correct, self.num_bins)
        self.pooled = self.pooled + bins
        ece = bins.ece
        if not math.isnan(ece):
            self.scan_eces.append(ece)
        return ece

    def merge(self, other: CalibrationAccumulator) -> None:
        """Add another accumulator's scans (e.g. gathered from another process)."""
        self.scan_eces.extend(other.scan_eces)
        self.pooled = self.pooled + other.pooled

    @property
    def ece_per_scan(self) -> float:
        """Unweighted mean of per-scan ECEs (the Calib3D number); nan before any scan."""
        if not self.scan_eces:
            return math.nan
        return float(np.mean(self.scan_eces))

    @property
    def ece_pooled(self) -> float:
        """ECE with every point of the set in one pool of bins; nan before any point."""
        return self.pooled.ece


DISTANCE_BANDS = (0.0, 10.0, 20.0, 30.0, 50.0)  # m, horizontal range from the sensor; the last band is open


class DistanceBands:
    """One confusion matrix per band of horizontal range (where in the scan a segmentor gains or loses)."""

    def __init__(self, num_classes: int, ignore_index: int | None, edges: tuple[float, ...] = DISTANCE_BANDS):
        self.edges = tuple(float(e) for e in edges)
        self.matrices = [ConfusionMatrix(num_classes, ignore_index) for _ in self.edges]

    def update(self, pred: Array, target: Array, points: Array) -> None:
        """Add one scan: pred, target (N,) train ids, points (N, >=2) whose x, y give the range."""
        xy = _as_tensor(points)[:, :2].float()
        band = torch.bucketize(torch.linalg.vector_norm(xy, dim=1), torch.tensor(self.edges[1:]), right=True)  # (N,)
        pred, target = _as_tensor(pred), _as_tensor(target)
        for index, matrix in enumerate(self.matrices):
            keep = band == index
            if bool(keep.any()):
                matrix.update(pred[keep], target[keep])

    def merge_matrices(self, matrices: list[np.ndarray]) -> None:
        """Add (K, K) counts per band (gathered from another process)."""
        for matrix, counts in zip(self.matrices, matrices):
            matrix.update_matrix(counts)

    def summary(self, class_names: tuple[str, ...]) -> list[dict]:
        """Per band: {"range": [lo, hi or None], "points", "miou", "iou" (null where absent)}."""
        rows = []
        for index, matrix in enumerate(self.matrices):
            counts = matrix.matrix
            iou = iou_per_class(counts)
            miou = mean_iou(counts)
            high = self.edges[index + 1] if index + 1 < len(self.edges) else None
            rows.append(
                {
                    "range": [self.edges[index], high],
                    "points": int(counts.sum()),
                    "miou": None if math.isnan(miou) else miou,
                    "iou": {name: (None if math.isnan(v) else float(v)) for name, v in zip(class_names, iou)},
                }
            )
        return rows


def summarize(cm: ConfusionMatrix, calibration: CalibrationAccumulator, class_names: tuple[str, ...] = ()) -> dict:
    """Json-ready summary: per-class IoU (null where absent), mIoU, both ECEs and the pooled bins."""
    iou = iou_per_class(cm.matrix)
    names = list(class_names) if class_names else [str(k) for k in range(len(iou))]
    miou = mean_iou(cm.matrix)
    return {
        "miou": None if math.isnan(miou) else miou,
        "iou": {n: (None if math.isnan(v) else float(v)) for n, v in zip(names, iou)},
        "ece_per_scan": None if math.isnan(calibration.ece_per_scan) else calibration.ece_per_scan,
        "ece_pooled": None if math.isnan(calibration.ece_pooled) else calibration.ece_pooled,
        "num_scans": len(calibration.scan_eces),
        "bins": calibration.pooled.to_dict(),
        "confusion": cm.matrix.tolist(),  # (K, K) point counts, rows = ground truth, columns = prediction
    }
