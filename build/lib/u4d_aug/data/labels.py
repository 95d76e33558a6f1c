"""Label maps: SemanticKITTI raw ids -> 19 train ids, nuScenes-lidarseg raw ids -> 16 train ids (mmdet3d).

Source: ../shared/reference/segmentation_protocols.md §5 (LaserMix b72cbd3 `semantickitti.yaml`,
`nuscenes/label_mapping.py`). Train ids are 0..K-1 with one ignore id K (19 for SemanticKITTI, 16 for
nuScenes); the conversion happens once, at load time. A `LabelSet` bundles one dataset's classes, ignore id and
map, so that the segmentation host takes them as a setting (`label_set(name)`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = [
    "LABEL_SET_NAMES",
    "LabelSet",
    "label_set",
    "SEMANTICKITTI_LABELS",
    "NUSCENES_LABELS",
    "semantickitti_to_nuscenes_raw",
    "SEMANTICKITTI_CLASSES",
    "SEMANTICKITTI_IGNORE",
    "SEMANTICKITTI_RAW_NAMES",
    "SEMANTICKITTI_LEARNING_MAP",
    "SEMANTICKITTI_INVERSE_MAP",
    "map_semantickitti",
    "unmap_semantickitti",
    "NUSCENES_CLASSES",
    "NUSCENES_IGNORE",
    "NUSCENES_RAW_NAMES",
    "NUSCENES_LEARNING_MAP",
    "map_nuscenes",
]

# ------------------------------------------------------------------------------------------------------------
# SemanticKITTI

SEMANTICKITTI_CLASSES: tuple[str, ...] = (
    "car",
    "bicycle",
    "motorcycle",
    "truck",
    "other-vehicle",
    "person",
    "bicyclist",
    "motorcyclist",
    "road",
    "parking",
    "sidewalk",
    "other-ground",
    "building",
    "fence",
    "vegetation",
    "trunk",
    "terrain",
    "pole",
    "traffic-sign",
)
SEMANTICKITTI_IGNORE = 19

# All raw ids of the official semantic-kitti.yaml `labels:` section.
SEMANTICKITTI_RAW_NAMES: dict[int, str] = {
    0: "unlabeled",
    1: "outlier",
    10: "car",
    11: "bicycle",
    13: "bus",
    15: "motorcycle",
    16: "on-rails",
    18: "truck",
    20: "other-vehicle",
    30: "person",
    31: "bicyclist",
    32: "motorcyclist",
    40: "road",
    44: "parking",
    48: "sidewalk",
    49: "other-ground",
    50: "building",
    51: "fence",
    52: "other-structure",
    60: "lane-marking",
    70: "vegetation",
    71: "trunk",
    72: "terrain",
    80: "pole",
    81: "traffic-sign",
    99: "other-object",
    252: "moving-car",
    253: "moving-bicyclist",
    254: "moving-person",
    255: "moving-motorcyclist",
    256: "moving-on-rails",
    257: "moving-bus",
    258: "moving-truck",
    259: "moving-other-vehicle",
}

# learning_map (mmdet3d/LaserMix: train ids 0..18, 19 = ignore); moving-* fold into their static class.
SEMANTICKITTI_LEARNING_MAP: dict[int, int] = {
    0: 19, 1: 19, 10: 0, 11: 1, 13: 4, 15: 2, 16: 4, 18: 3, 20: 4, 30: 5, 31: 6, 32: 7,
    40: 8, 44: 9, 48: 10, 49: 11, 50: 12, 51: 13, 52: 19, 60: 8, 70: 14, 71: 15, 72: 16,
    80: 17, 81: 18, 99: 19, 252: 0, 253: 6, 254: 5, 255: 7, 256: 4, 257: 4, 258: 3, 259: 4,
}  # fmt: skip

# learning_map_inv: train id -> the raw id written for it (generated banks); ignore -> 0 unlabeled.
SEMANTICKITTI_INVERSE_MAP: dict[int, int] = {
    0: 10, 1: 11, 2: 15, 3: 18, 4: 20, 5: 30, 6: 31, 7: 32, 8: 40, 9: 44,
    10: 48, 11: 49, 12: 50, 13: 51, 14: 70, 15: 71, 16: 72, 17: 80, 18: 81, 19: 0,
}  # fmt: skip

_KITTI_LUT = np.full(1 << 16, SEMANTICKITTI_IGNORE, dtype=np.int64)  # raw id (16 bits) -> train id
for _raw, _train in SEMANTICKITTI_LEARNING_MAP.items():
    _KITTI_LUT[_raw] = _train
_KITTI_INV_LUT = np.array([SEMANTICKITTI_INVERSE_MAP[i] for i in range(SEMANTICKITTI_IGNORE + 1)], dtype=np.uint16)


def map_semantickitti(raw: np.ndarray) -> np.ndarray:
    """Raw SemanticKITTI ids (low 16 bits count) -> train ids 0..18, 19 for ignore and unknown ids."""
    raw = np.asarray(raw)
    if not np.issubdtype(raw.dtype, np.integer):
        raise TypeError(f"map_semantickitti expects integer label ids, got dtype {raw.dtype}")
    return _KITTI_LUT[raw.astype(np.int64) & 0xFFFF]


def unmap_semantickitti(train_ids: np.ndarray) -> np.ndarray:
    """Train ids 0..19 -> raw SemanticKITTI ids (uint16) by the inverse learning map (for written banks)."""
    train_ids = np.asarray(train_ids)
    if train_ids.size and (train_ids.min() < 0 or train_ids.max() > SEMANTICKITTI_IGNORE):
        raise ValueError(f"train ids must lie in 0..{SEMANTICKITTI_IGNORE}, got {train_ids.min()}..{train_ids.max()}")
    return _KITTI_INV_LUT[train_ids.astype(np.int64)]


# ------------------------------------------------------------------------------------------------------------
# nuScenes-lidarseg

NUSCENES_CLASSES: tuple[str, ...] = (
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
)
NUSCENES_IGNORE = 16

NUSCENES_RAW_NAMES: dict[int, str] = {
    0: "noise",
    1: "animal",
    2: "human.pedestrian.adult",
    3: "human.pedestrian.child",
    4: "human.pedestrian.construction_worker",
    5: "human.pedestrian.personal_mobility",
    6: "human.pedestrian.police_officer",
    7: "human.pedestrian.stroller",
    8: "human.pedestrian.wheelchair",
    9: "movable_object.barrier",
    10: "movable_object.debris",
    11: "movable_object.pushable_pullable",
    12: "movable_object.trafficcone",
    13: "static_object.bicycle_rack",
    14: "vehicle.bicycle",
    15: "vehicle.bus.bendy",
    16: "vehicle.bus.rigid",
    17: "vehicle.car",
    18: "vehicle.construction",
    19: "vehicle.emergency.ambulance",
    20: "vehicle.emergency.police",
    21: "vehicle.motorcycle",
    22: "vehicle.trailer",
    23: "vehicle.truck",
    24: "flat.driveable_surface",
    25: "flat.other",
    26: "flat.sidewalk",
    27: "flat.terrain",
    28: "static.manmade",
    29: "static.other",
    30: "static.vegetation",
    31: "vehicle.ego",
}

NUSCENES_LEARNING_MAP: dict[int, int] = {
    0: 16, 1: 16, 2: 6, 3: 6, 4: 6, 5: 16, 6: 6, 7: 16, 8: 16, 9: 0, 10: 16, 11: 16, 12: 7, 13: 16, 14: 1,
    15: 2, 16: 2, 17: 3, 18: 4, 19: 16, 20: 16, 21: 5, 22: 8, 23: 9, 24: 10, 25: 11, 26: 12, 27: 13, 28: 14,
    29: 16, 30: 15, 31: 16,
}  # fmt: skip

_NUSCENES_LUT = np.full(256, NUSCENES_IGNORE, dtype=np.int64)  # raw uint8 id -> train id (ids > 31 -> ignore)
for _raw, _train in NUSCENES_LEARNING_MAP.items():
    _NUSCENES_LUT[_raw] = _train


def map_nuscenes(raw: np.ndarray) -> np.ndarray:
    """Raw nuScenes-lidarseg ids (uint8, 0..31) -> train ids 0..15, 16 for ignore and unknown ids."""
    raw = np.asarray(raw)
    if not np.issubdtype(raw.dtype, np.integer):
        raise TypeError(f"map_nuscenes expects integer label ids, got dtype {raw.dtype}")
    raw = raw.astype(np.int64)
    out = np.full(raw.shape, NUSCENES_IGNORE, dtype=np.int64)
    valid = (raw >= 0) & (raw < 256)
    out[valid] = _NUSCENES_LUT[raw[valid]]
    return out


# ------------------------------------------------------------------------------------------------------------
# the simulated world (SemanticKITTI raw ids) written as nuScenes-lidarseg

# Our reading of the two class definitions (nuScenes lidarseg README): vans are vehicle.car, a rider is annotated
# with the two-wheeler, parking lots are driveable surface, trunks are vegetation, poles, signs, fences and other
# structures (sheds, which SemanticKITTI ignores) are static.manmade, buses vehicle.bus.rigid; unlabeled, outlier,
# on-rails and other-object stay ignored (noise, static.other).
SEMANTICKITTI_TO_NUSCENES_RAW: dict[int, int] = {
    0: 0, 1: 0, 10: 17, 11: 14, 13: 16, 15: 21, 16: 0, 18: 23, 20: 17, 30: 2, 31: 14, 32: 21,
    40: 24, 44: 24, 48: 26, 49: 25, 50: 28, 51: 28, 52: 28, 60: 24, 70: 30, 71: 30, 72: 27,
    80: 28, 81: 28, 99: 29, 252: 17, 253: 14, 254: 2, 255: 21, 256: 0, 257: 16, 258: 23, 259: 17,
}  # fmt: skip

_KITTI_TO_NUSCENES_LUT = np.zeros(1 << 16, dtype=np.uint8)  # raw SemanticKITTI id -> raw lidarseg id (0 = noise)
for _raw, _nuscenes in SEMANTICKITTI_TO_NUSCENES_RAW.items():
    _KITTI_TO_NUSCENES_LUT[_raw] = _nuscenes


def semantickitti_to_nuscenes_raw(raw: np.ndarray) -> np.ndarray:
    """Raw SemanticKITTI ids (low 16 bits) -> raw nuScenes-lidarseg ids (uint8), unknown ids -> 0 noise."""
    raw = np.asarray(raw)
    if not np.issubdtype(raw.dtype, np.integer):
        raise TypeError(f"semantickitti_to_nuscenes_raw expects integer label ids, got dtype {raw.dtype}")
    return _KITTI_TO_NUSCENES_LUT[raw.astype(np.int64) & 0xFFFF]


# ------------------------------------------------------------------------------------------------------------
# label sets: what the segmentation host reads as a setting

LabelSetName = Literal["semantickitti", "nuscenes"]
LABEL_SET_NAMES: tuple[str, ...] = ("semantickitti", "nuscenes")


@dataclass(frozen=True)
class LabelSet:
    """One dataset's training classes: names (train ids 0..K-1), the ignore id K, raw id -> train id map."""

    name: LabelSetName
    classes: tuple[str, ...]
    ignore_index: int
    learning_map: Mapping[int, int]
    raw_names: Mapping[int, str]
    things: tuple[str, ...]  # the rarer object classes (PolarMix's default paste classes)

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    def to_train_ids(self, raw: np.ndarray) -> np.ndarray:
        """Raw ids of this dataset -> train ids (N,) int64, the ignore id for ignored and unknown ids."""
        if self.name == "semantickitti":
            return map_semantickitti(raw)
        elif self.name == "nuscenes":
            return map_nuscenes(raw)
        raise ValueError(f"label set {self.name!r}: expected one of {', '.join(LABEL_SET_NAMES)}")


SEMANTICKITTI_LABELS = LabelSet(
    name="semantickitti",
    classes=SEMANTICKITTI_CLASSES,
    ignore_index=SEMANTICKITTI_IGNORE,
    learning_map=SEMANTICKITTI_LEARNING_MAP,
    raw_names=SEMANTICKITTI_RAW_NAMES,
    things=SEMANTICKITTI_CLASSES[1:8],  # bicycle .. motorcyclist (car is common enough)
)
NUSCENES_LABELS = LabelSet(
    name="nuscenes",
    classes=NUSCENES_CLASSES,
    ignore_index=NUSCENES_IGNORE,
    learning_map=NUSCENES_LEARNING_MAP,
    raw_names=NUSCENES_RAW_NAMES,
    # the vehicles and people but car, and the traffic cones (barriers line roads by the dozen)
    things=("bicycle", "bus", "construction_vehicle", "motorcycle", "pedestrian", "traffic_cone", "trailer", "truck"),
)


def label_set(name: str) -> LabelSet:
    """The label set of a dataset format: 'semantickitti' (19 classes, ignore 19) or 'nuscenes' (16, ignore 16)."""
    if name == "semantickitti":
        return SEMANTICKITTI_LABELS
    elif name == "nuscenes":
        return NUSCENES_LABELS
    raise ValueError(f"unknown label set {name!r}; expected one of {', '.join(LABEL_SET_NAMES)}")
