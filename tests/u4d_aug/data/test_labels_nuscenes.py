"""The nuScenes label set as a segmentation setting: the 16-class map on the real 40-point lidarseg sample read
through the v1.0 tables, label sets by name, the simulated world's raw-id map, SegTrainConfig resolution."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from segmentation.config import SegTrainConfig, class_names
from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.data.datasets import NuscenesScanDataset, ScanDataset
from u4d_aug.data.labels import (
    NUSCENES_CLASSES,
    NUSCENES_LABELS,
    SEMANTICKITTI_CLASSES,
    SEMANTICKITTI_LABELS,
    SEMANTICKITTI_RAW_NAMES,
    label_set,
    map_nuscenes,
    map_semantickitti,
    semantickitti_to_nuscenes_raw,
)
from u4d_aug.data.nuscenes import LidarFrame, pose_matrix, write_nuscenes_tables
from u4d_aug.errors import InputError

SAMPLE_40 = (
    "nuscenes_mmdet3d_tests/samples/LIDAR_TOP/n015-2018-08-02-17-16-37+0800__LIDAR_TOP__1533201470948018.pcd.bin"
)
TOKEN_40 = "5f6c1e0a0c3b444b97e78d2aa3fa34d2"
LIDARSEG_40 = f"nuscenes_mmdet3d_tests/lidarseg/v1.0-trainval/{TOKEN_40}_lidarseg.bin"
TINY_SEG = REPO / "configs" / "seg" / "tiny.yaml"


@pytest.fixture
def root_40(real_root: Path, tmp_path: Path) -> Path:
    """A nuScenes root in tmp_path: tables written for the real 40-point sample, its files linked (not copied)."""
    if not (real_root / SAMPLE_40).is_file() or not (real_root / LIDARSEG_40).is_file():
        pytest.skip(f"nuScenes 40-point lidarseg sample not found under {real_root}")
    for relative in (SAMPLE_40, LIDARSEG_40):
        target = tmp_path / relative.split("/", 1)[1]
        target.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(real_root / relative, target)
    frame = LidarFrame(
        token=TOKEN_40,
        timestamp=1533201470948018,
        is_key_frame=True,
        filename=SAMPLE_40.split("/", 1)[1],
        ego_to_world=np.eye(4),
        lidar_to_ego=pose_matrix([0.94, 0.0, 1.84], [1.0, 0.0, 0.0, 0.0]),
        lidarseg=LIDARSEG_40.split("/", 1)[1],
    )
    write_nuscenes_tables(tmp_path, {"scene-0001": [frame]})
    return tmp_path


def test_real_40_point_sample_maps_to_the_16_classes(root_40: Path) -> None:
    """SOURCES.md: 17 car = 2, 24 driveable = 15, 27 terrain = 1, 28 manmade = 12, 30 vegetation = 1, 31 ego = 9."""
    scans = NuscenesScanDataset(root_40, labeled_only=True, remove_close=0.0)
    item = scans[0]
    assert item["seq"] == "scene-0001" and item["frame"] == TOKEN_40 and item["points"].shape == (40, 4)
    counts = np.bincount(item["labels"], minlength=NUSCENES_LABELS.ignore_index + 1)
    names = [*NUSCENES_LABELS.classes, "ignore"]
    assert {names[i]: int(c) for i, c in enumerate(counts) if c} == {
        "car": 2,
        "driveable_surface": 15,
        "terrain": 1,
        "manmade": 12,
        "vegetation": 1,
        "ignore": 9,  # vehicle.ego
    }
    assert counts[16] == 9 and NUSCENES_LABELS.ignore_index == 16
    # the default drops the returns within 1 m of the sensor, labels with them: 7 of the 9 ego points
    near = NuscenesScanDataset(root_40)[0]
    assert len(near["points"]) == len(near["labels"]) == 33
    assert int((near["labels"] == 16).sum()) == 2 and int((near["labels"] == 10).sum()) == 15
    assert scans.train_ids(0).tolist() == item["labels"].tolist()


def test_label_sets_by_name() -> None:
    assert label_set("semantickitti") is SEMANTICKITTI_LABELS and label_set("nuscenes") is NUSCENES_LABELS
    assert (NUSCENES_LABELS.num_classes, NUSCENES_LABELS.ignore_index) == (16, 16)
    assert (SEMANTICKITTI_LABELS.num_classes, SEMANTICKITTI_LABELS.ignore_index) == (19, 19)
    raw = np.arange(40)
    np.testing.assert_array_equal(NUSCENES_LABELS.to_train_ids(raw), map_nuscenes(raw))
    np.testing.assert_array_equal(SEMANTICKITTI_LABELS.to_train_ids(raw), map_semantickitti(raw))
    for labels in (NUSCENES_LABELS, SEMANTICKITTI_LABELS):
        assert set(labels.things) <= set(labels.classes) and len(set(labels.things)) == len(labels.things)
        assert set(labels.learning_map.values()) == set(range(labels.num_classes + 1))
    assert ScanDataset.label_set is SEMANTICKITTI_LABELS and NuscenesScanDataset.label_set is NUSCENES_LABELS
    with pytest.raises(ValueError, match="unknown label set 'kitti360'"):
        label_set("kitti360")


# the class each SemanticKITTI train class becomes when the simulated world is written as nuScenes lidarseg
SIM_CLASS = {
    "car": "car", "bicycle": "bicycle", "motorcycle": "motorcycle", "truck": "truck", "other-vehicle": "car",
    "person": "pedestrian", "bicyclist": "bicycle", "motorcyclist": "motorcycle", "road": "driveable_surface",
    "parking": "driveable_surface", "sidewalk": "sidewalk", "other-ground": "other_flat", "building": "manmade",
    "fence": "manmade", "vegetation": "vegetation", "trunk": "vegetation", "terrain": "terrain", "pole": "manmade",
    "traffic-sign": "manmade", "ignore": "ignore",
}  # fmt: skip


# raw ids whose nuScenes class is not their SemanticKITTI class's: bus (other-vehicle there), on-rails (no class),
# other-structure (ignored there, manmade in nuScenes)
SIM_RAW_EXCEPTIONS = {13: "bus", 257: "bus", 16: "ignore", 256: "ignore", 52: "manmade"}


def test_simulated_world_raw_ids_become_the_matching_nuscenes_classes() -> None:
    kitti_names, nuscenes_names = [*SEMANTICKITTI_CLASSES, "ignore"], [*NUSCENES_CLASSES, "ignore"]
    for raw in SEMANTICKITTI_RAW_NAMES:
        kitti = kitti_names[int(map_semantickitti(np.array([raw]))[0])]
        nuscenes = nuscenes_names[int(map_nuscenes(semantickitti_to_nuscenes_raw(np.array([raw])))[0])]
        assert nuscenes == SIM_RAW_EXCEPTIONS.get(raw, SIM_CLASS[kitti]), (raw, kitti, nuscenes)
    out = semantickitti_to_nuscenes_raw(np.array([10, 0x0005000A, 777], dtype=np.uint32))
    assert out.dtype == np.uint8 and out.tolist() == [17, 17, 0]  # instance bits ignored; unknown ids -> noise


def test_segmentation_takes_classes_and_ignore_id_from_the_data_format(tmp_path: Path) -> None:
    kitti = load_config(SegTrainConfig, TINY_SEG, [f"out_dir={tmp_path}"])
    assert kitti.data.format == "semantickitti" and kitti.data.label_set is SEMANTICKITTI_LABELS
    assert kitti.augment.paste_classes == list(SEMANTICKITTI_CLASSES[1:8])  # the default, as before
    assert class_names(kitti) == list(SEMANTICKITTI_CLASSES)
    nus = load_config(SegTrainConfig, TINY_SEG, ["data.format=nuscenes", "model.num_classes=16"])
    assert nus.data.label_set.ignore_index == 16 and class_names(nus) == list(NUSCENES_CLASSES)
    assert nus.augment.paste_classes == list(NUSCENES_LABELS.things)
    with pytest.raises(InputError, match=r"paste_classes: unknown class names \['bicyclist'\]; valid: \['barrier'"):
        load_config(SegTrainConfig, TINY_SEG, ["data.format=nuscenes", "augment.paste_classes=[bicyclist]"])
    with pytest.raises(InputError, match="data.format"):
        load_config(SegTrainConfig, TINY_SEG, ["data.format=waymo"])
