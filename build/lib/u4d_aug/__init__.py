"""u4d-aug: uncertainty-aware 4D LiDAR scene synthesis (U4D) as a segmentation data-augmentation plugin.

The public API (README "API"); each name is imported from its module on first use, so `import u4d_aug` stays
cheap (no torch until a name that needs it is touched).
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# public name -> the module that defines it
_EXPORTS: dict[str, str] = {
    # reading scans and labels
    "Scan": "u4d_aug.data.scan",
    "read_scan": "u4d_aug.data.scan",
    "read_kitti_scan": "u4d_aug.data.formats",
    "read_kitti_label": "u4d_aug.data.formats",
    "write_kitti_scan": "u4d_aug.data.formats",
    "read_nuscenes_scan": "u4d_aug.data.formats",
    "read_nuscenes_lidarseg": "u4d_aug.data.formats",
    "map_semantickitti": "u4d_aug.data.labels",
    "map_nuscenes": "u4d_aug.data.labels",
    "SEMANTICKITTI_CLASSES": "u4d_aug.data.labels",
    "SEMANTICKITTI_IGNORE": "u4d_aug.data.labels",
    "NUSCENES_CLASSES": "u4d_aug.data.labels",
    "NUSCENES_IGNORE": "u4d_aug.data.labels",
    "LabelSet": "u4d_aug.data.labels",
    "label_set": "u4d_aug.data.labels",
    "read_nuscenes_index": "u4d_aug.data.nuscenes",
    # sensors and the range view
    "Sensor": "u4d_aug.data.sensors",
    "get_sensor": "u4d_aug.data.sensors",
    "Projection": "u4d_aug.range_view",
    "project": "u4d_aug.range_view",
    "project_batch": "u4d_aug.range_view",
    "unproject": "u4d_aug.range_view",
    "to_image": "u4d_aug.range_view",
    "scatter_to_image": "u4d_aug.range_view",
    # uncertainty
    "entropy": "u4d_aug.uncertainty",
    "select_uncertain": "u4d_aug.uncertainty",
    "uncertain_range_view": "u4d_aug.uncertainty",
    "load_probs": "u4d_aug.uncertainty",
    # generation
    "load_generator": "u4d_aug.pipeline",
    "generate_u4d": "u4d_aug.pipeline",
    "generate_baseline": "u4d_aug.pipeline",
    "complete": "u4d_aug.pipeline",
    "to_points": "u4d_aug.pipeline",
    "GeneratedScans": "u4d_aug.generated",
    # datasets, banks and batching
    "ScanDataset": "u4d_aug.data.datasets",
    "SequenceDataset": "u4d_aug.data.datasets",
    "NuscenesScanDataset": "u4d_aug.data.datasets",
    "NuscenesSequenceDataset": "u4d_aug.data.datasets",
    "open_scans": "u4d_aug.data.datasets",
    "open_sequences": "u4d_aug.data.datasets",
    "collate_scans": "u4d_aug.data.collate",
    "split_points": "u4d_aug.data.collate",
    "read_manifest": "u4d_aug.bank",
    # configs and errors
    "load_config": "u4d_aug.config",
    "resolve_config_path": "u4d_aug.presets",
    "list_presets": "u4d_aug.presets",
    "InputError": "u4d_aug.errors",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str) -> Any:
    """Import a public name from its module on first access (PEP 562)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'u4d_aug' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
