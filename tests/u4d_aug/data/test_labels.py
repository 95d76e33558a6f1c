"""Label maps against the tables of segmentation_protocols.md §5."""

from __future__ import annotations

import numpy as np
import pytest

from u4d_aug.data.labels import (
    NUSCENES_CLASSES,
    NUSCENES_IGNORE,
    NUSCENES_LEARNING_MAP,
    NUSCENES_RAW_NAMES,
    SEMANTICKITTI_CLASSES,
    SEMANTICKITTI_IGNORE,
    SEMANTICKITTI_LEARNING_MAP,
    SEMANTICKITTI_RAW_NAMES,
    map_nuscenes,
    map_semantickitti,
    unmap_semantickitti,
)

# segmentation_protocols.md §5, SemanticKITTI learning_map table: train id -> raw ids
KITTI_TABLE = {
    0: (10, 252), 1: (11,), 2: (15,), 3: (18, 258), 4: (13, 16, 20, 256, 257, 259), 5: (30, 254),
    6: (31, 253), 7: (32, 255), 8: (40, 60), 9: (44,), 10: (48,), 11: (49,), 12: (50,), 13: (51,),
    14: (70,), 15: (71,), 16: (72,), 17: (80,), 18: (81,), 19: (0, 1, 52, 99),
}  # fmt: skip

# segmentation_protocols.md §5, nuScenes 16-class table
NUSCENES_TABLE = {
    0: (9,), 1: (14,), 2: (15, 16), 3: (17,), 4: (18,), 5: (21,), 6: (2, 3, 4, 6), 7: (12,), 8: (22,),
    9: (23,), 10: (24,), 11: (25,), 12: (26,), 13: (27,), 14: (28,), 15: (30,),
    16: (0, 1, 5, 7, 8, 10, 11, 13, 19, 20, 29, 31),
}  # fmt: skip


def test_semantickitti_map_matches_protocol_table():
    assert len(SEMANTICKITTI_CLASSES) == 19 and SEMANTICKITTI_IGNORE == 19
    assert SEMANTICKITTI_CLASSES[4] == "other-vehicle" and SEMANTICKITTI_CLASSES[15] == "trunk"
    table = {raw: train for train, raws in KITTI_TABLE.items() for raw in raws}
    assert table == SEMANTICKITTI_LEARNING_MAP
    assert set(SEMANTICKITTI_RAW_NAMES) == set(table)  # every raw id of semantic-kitti.yaml is mapped
    assert len(SEMANTICKITTI_RAW_NAMES) == 34 and SEMANTICKITTI_RAW_NAMES[255] == "moving-motorcyclist"
    raw = np.array(sorted(table), dtype=np.uint16)
    np.testing.assert_array_equal(map_semantickitti(raw), [table[r] for r in raw])


def test_semantickitti_unknown_ids_and_high_bits():
    assert map_semantickitti(np.array([2, 12, 100, 260, 65535], dtype=np.uint32)).tolist() == [19] * 5
    # instance in the high 16 bits is ignored; int32 loading (mmdet3d) gives negatives for big instances
    full = np.array([(7 << 16) | 10, (0xFFFF << 16) | 81], dtype=np.uint32)
    assert map_semantickitti(full).tolist() == [0, 18]
    assert map_semantickitti(full.view(np.int32)).tolist() == [0, 18]
    assert map_semantickitti(np.zeros((2, 3), dtype=np.uint16)).shape == (2, 3)
    assert map_semantickitti(np.array([10])).dtype == np.int64
    with pytest.raises(TypeError):
        map_semantickitti(np.array([1.0]))


def test_semantickitti_inverse_map_round_trip():
    train = np.arange(SEMANTICKITTI_IGNORE + 1)
    raw = unmap_semantickitti(train)
    assert raw.dtype == np.uint16 and raw[SEMANTICKITTI_IGNORE] == 0
    np.testing.assert_array_equal(map_semantickitti(raw), train)
    with pytest.raises(ValueError):
        unmap_semantickitti(np.array([20]))


def test_nuscenes_map_matches_protocol_table():
    assert len(NUSCENES_CLASSES) == 16 and NUSCENES_IGNORE == 16
    table = {raw: train for train, raws in NUSCENES_TABLE.items() for raw in raws}
    assert table == NUSCENES_LEARNING_MAP
    assert set(NUSCENES_RAW_NAMES) == set(range(32)) and NUSCENES_RAW_NAMES[31] == "vehicle.ego"
    raw = np.arange(32, dtype=np.uint8)
    np.testing.assert_array_equal(map_nuscenes(raw), [table[r] for r in range(32)])
    assert map_nuscenes(np.array([32, 200, 255], dtype=np.uint8)).tolist() == [16, 16, 16]
    assert map_nuscenes(np.array([-1, 300])).tolist() == [16, 16]
    assert map_nuscenes(raw).dtype == np.int64
