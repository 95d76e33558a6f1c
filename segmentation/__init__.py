"""Downstream segmentation host: sparse-free voxel nets, LaserMix mean teacher, mIoU/ECE.

The public API (README "API"); each name is imported from its module on first use, so `import segmentation`
stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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


# Type checkers read the real types from these imports; at run time `__getattr__` imports each name on first use
# (tests/test_typing.py checks that they cover `__all__`, each from the module `_EXPORTS` names).
if TYPE_CHECKING:
    # `X as X` marks a re-export; isort would give each such name its own statement
    # isort: off
    from segmentation.models import (
        SegModelConfig as SegModelConfig,
        build_model as build_model,
        MinkUNet as MinkUNet,
        SPVCNN as SPVCNN,
    )
    from segmentation.mean_teacher import (
        MeanTeacherConfig as MeanTeacherConfig,
        make_teacher as make_teacher,
        teacher_mode as teacher_mode,
        ema_update as ema_update,
        pseudo_labels as pseudo_labels,
    )
    from segmentation.semi import semi_step as semi_step
    from segmentation.config import SegTrainConfig as SegTrainConfig
    from segmentation.train import supervised_step as supervised_step
    from segmentation.metrics import (
        confusion_matrix as confusion_matrix,
        ConfusionMatrix as ConfusionMatrix,
        iou_per_class as iou_per_class,
        mean_iou as mean_iou,
        top_label as top_label,
        reliability_bins as reliability_bins,
        ReliabilityBins as ReliabilityBins,
        expected_calibration_error as expected_calibration_error,
        scan_ece as scan_ece,
        CalibrationAccumulator as CalibrationAccumulator,
        summarize as summarize,
    )
    from segmentation.plots import plot_reliability as plot_reliability
    from segmentation.predict import (
        load_checkpoint as load_checkpoint,
        model_from_checkpoint as model_from_checkpoint,
        predict_probs as predict_probs,
    )
    # isort: on
else:

    def __getattr__(name: str) -> Any:
        """Import a public name from its module on first access (PEP 562)."""
        if name not in _EXPORTS:
            raise AttributeError(f"module 'segmentation' has no attribute {name!r}")
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
