"""u4d-aug: uncertainty-aware 4D LiDAR scene synthesis (U4D) as a segmentation data-augmentation plugin.

The public API (README "API"); each name is imported from its module on first use, so `import u4d_aug` stays
cheap (no torch until a name that needs it is touched).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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
    "LoadedGenerator": "u4d_aug.pipeline",
    "generate_u4d": "u4d_aug.pipeline",
    "generate_baseline": "u4d_aug.pipeline",
    "complete": "u4d_aug.pipeline",
    "to_points": "u4d_aug.pipeline",
    "GeneratedScans": "u4d_aug.generated",
    "SamplingSettings": "u4d_aug.sampling_settings",
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


# Type checkers read the real types from these imports; at run time `__getattr__` imports each name on first use
# (tests/test_typing.py checks that they cover `__all__`, each from the module `_EXPORTS` names).
if TYPE_CHECKING:
    # `X as X` marks a re-export; isort would give each such name its own statement
    # isort: off
    from u4d_aug.data.scan import Scan as Scan, read_scan as read_scan
    from u4d_aug.data.formats import (
        read_kitti_scan as read_kitti_scan,
        read_kitti_label as read_kitti_label,
        write_kitti_scan as write_kitti_scan,
        read_nuscenes_scan as read_nuscenes_scan,
        read_nuscenes_lidarseg as read_nuscenes_lidarseg,
    )
    from u4d_aug.data.labels import (
        map_semantickitti as map_semantickitti,
        map_nuscenes as map_nuscenes,
        SEMANTICKITTI_CLASSES as SEMANTICKITTI_CLASSES,
        SEMANTICKITTI_IGNORE as SEMANTICKITTI_IGNORE,
        NUSCENES_CLASSES as NUSCENES_CLASSES,
        NUSCENES_IGNORE as NUSCENES_IGNORE,
        LabelSet as LabelSet,
        label_set as label_set,
    )
    from u4d_aug.data.nuscenes import read_nuscenes_index as read_nuscenes_index
    from u4d_aug.data.sensors import Sensor as Sensor, get_sensor as get_sensor
    from u4d_aug.range_view import (
        Projection as Projection,
        project as project,
        project_batch as project_batch,
        unproject as unproject,
        to_image as to_image,
        scatter_to_image as scatter_to_image,
    )
    from u4d_aug.uncertainty import (
        entropy as entropy,
        select_uncertain as select_uncertain,
        uncertain_range_view as uncertain_range_view,
        load_probs as load_probs,
    )
    from u4d_aug.pipeline import (
        load_generator as load_generator,
        LoadedGenerator as LoadedGenerator,
        generate_u4d as generate_u4d,
        generate_baseline as generate_baseline,
        complete as complete,
        to_points as to_points,
    )
    from u4d_aug.generated import GeneratedScans as GeneratedScans
    from u4d_aug.sampling_settings import SamplingSettings as SamplingSettings
    from u4d_aug.data.datasets import (
        ScanDataset as ScanDataset,
        SequenceDataset as SequenceDataset,
        NuscenesScanDataset as NuscenesScanDataset,
        NuscenesSequenceDataset as NuscenesSequenceDataset,
        open_scans as open_scans,
        open_sequences as open_sequences,
    )
    from u4d_aug.data.collate import collate_scans as collate_scans, split_points as split_points
    from u4d_aug.bank import read_manifest as read_manifest
    from u4d_aug.config import load_config as load_config
    from u4d_aug.presets import resolve_config_path as resolve_config_path, list_presets as list_presets
    from u4d_aug.errors import InputError as InputError
    # isort: on
else:

    def __getattr__(name: str) -> Any:
        """Import a public name from its module on first access (PEP 562)."""
        if name not in _EXPORTS:
            raise AttributeError(f"module 'u4d_aug' has no attribute {name!r}")
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
