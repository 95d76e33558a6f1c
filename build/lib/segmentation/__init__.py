"""Downstream segmentation host: sparse-free voxel nets, LaserMix mean teacher, mIoU/ECE.

The public API (README "API"); each name is imported from its module on first use, so `import segmentation`
stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

# public name -> the module that defines it
_EXPORTS: dict[str, str] = {
    # nets
    "SegModelConfig": "segmentation.models",
    "build_model": "segmentation.models",
    "MinkUNet": "segmentation.models",
    "SPVCNN": "segmentation.models",
    # LaserMix mean teacher (the mixing itself: `segmentation.lasermix.lasermix`; a function named like its module is
    # not re-exported, so that `segmentation.lasermix` stays the module)
    "MeanTeacherConfig": "segmentation.mean_teacher",
    "make_teacher": "segmentation.mean_teacher",
    "teacher_mode": "segmentation.mean_teacher",
    "ema_update": "segmentation.mean_teacher",
    "pseudo_labels": "segmentation.mean_teacher",
    "semi_step": "segmentation.semi",
    # training (the loop itself: `segmentation.train.train`; a function named like its module is not re-exported,
    # so that `segmentation.train` stays the module)
    "SegTrainConfig": "segmentation.config",
    "supervised_step": "segmentation.train",
    # metrics: mIoU and ECE
    "confusion_matrix": "segmentation.metrics",
    "ConfusionMatrix": "segmentation.metrics",
    "iou_per_class": "segmentation.metrics",
    "mean_iou": "segmentation.metrics",
    "top_label": "segmentation.metrics",
    "reliability_bins": "segmentation.metrics",
    "ReliabilityBins": "segmentation.metrics",
    "expected_calibration_error": "segmentation.metrics",
    "scan_ece": "segmentation.metrics",
    "CalibrationAccumulator": "segmentation.metrics",
    "summarize": "segmentation.metrics",
    "plot_reliability": "segmentation.plots",
    # checkpoints -> probabilities (evaluation of a checkpoint: `segmentation.evaluate.evaluate`)
    "load_checkpoint": "segmentation.predict",
    "model_from_checkpoint": "segmentation.predict",
    "predict_probs": "segmentation.predict",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str) -> Any:
    """Import a public name from its module on first access (PEP 562)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'segmentation' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
