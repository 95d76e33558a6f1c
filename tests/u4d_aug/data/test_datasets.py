"""Scan / sequence datasets over a SemanticKITTI layout: tiny made-up roots and the real seq 00 sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from u4d_aug.data.datasets import (
    ScanDataset,
    SequenceDataset,
    detect_format,
    label_path_for,
    list_frames,
    list_sequences,
    resolve_sequences,
    scan_path,
)
from u4d_aug.data.formats import write_calib, write_kitti_label, write_kitti_scan, write_poses
from u4d_aug.errors import InputError


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pose = np.eye(4)
    pose[:3, :3] = q * np.sign(np.linalg.det(q))
    pose[:3, 3] = rng.normal(size=3) * 5
    return pose


def _make_root(root: Path, rng: np.random.Generator, frames: dict[str, int], labeled: int = 2) -> dict:
    """sequences/XX with `frames[XX]` scans (the first `labeled` with labels), calib.txt and poses.txt."""
    lidar_poses = {}
    for seq, count in frames.items():
        for i in range(count):
            points = rng.normal(size=(20 + i, 4)).astype(np.float32)
            write_kitti_scan(scan_path(root, seq, f"{i:06d}"), points)
            if i < labeled:
                write_kitti_label(label_path_for(scan_path(root, seq, f"{i:06d}")), np.full(20 + i, 40, np.uint16))
        calib = {"P0": rng.normal(size=(3, 4)), "Tr": _random_pose(rng)[:3]}
        write_calib(root / "sequences" / seq / "calib.txt", calib)
        lidar_poses[seq] = np.stack([_random_pose(rng) for _ in range(count)])
        write_poses(root / "sequences" / seq / "poses.txt", lidar_poses[seq], calib)
    return lidar_poses


def test_scan_dataset_items(tmp_path, rng):
    _make_root(tmp_path, rng, {"00": 3, "01": 2})
    (tmp_path / "sequences" / "notes").mkdir()  # folders without velodyne/ are not sequences
    assert list_sequences(tmp_path) == ["00", "01"]
    assert list_frames(tmp_path, "00") == ["000000", "000001", "000002"]
    dataset = ScanDataset(tmp_path)
    assert len(dataset) == 5
    item = dataset[2]
    assert item["seq"] == "00" and item["frame"] == "000002" and item["labels"] is None
    assert item["points"].shape == (22, 4) and item["points"].dtype == np.float32
    item = dataset[3]
    assert item["seq"] == "01" and item["labels"].dtype == np.int64 and set(item["labels"].tolist()) == {8}  # road
    assert len(ScanDataset(tmp_path, labeled_only=True)) == 4
    assert [e[0] for e in ScanDataset(tmp_path, sequences=[1]).entries] == ["01", "01"]
    assert resolve_sequences(tmp_path, ["00", 1]) == ["00", "01"]
    assert resolve_sequences(tmp_path, "00-01") == resolve_sequences(tmp_path, ["00-00", "01"]) == ["00", "01"]
    with pytest.raises(InputError, match="ends before it starts"):
        resolve_sequences(tmp_path, "01-00")
    with pytest.raises(InputError, match="sequences/02/velodyne"):
        resolve_sequences(tmp_path, "00-02")  # every sequence of the range must exist
    with pytest.raises(InputError, match="a range like '00-87'"):
        resolve_sequences(tmp_path, "trian")


def test_missing_velodyne_folder(tmp_path, rng):
    _raises = pytest.raises
    with _raises(InputError, match="sequences: folder not found"):
        ScanDataset(tmp_path)
    (tmp_path / "sequences" / "00").mkdir(parents=True)
    with _raises(InputError, match="no sequence has a velodyne/ folder"):
        list_sequences(tmp_path)
    with _raises(InputError, match=r"sequences/00/velodyne: velodyne/ folder not found") as info:
        ScanDataset(tmp_path, sequences=["00"])
    assert str(tmp_path / "sequences" / "00" / "velodyne") in str(info.value) and "\n" not in str(info.value)
    _make_root(tmp_path, rng, {"01": 2})
    with _raises(InputError, match=r"sequences/02/velodyne"):
        SequenceDataset(tmp_path, 2, sequences=["01", "02"])
    with _raises(InputError, match=r"sequences/00/velodyne"):  # the train split needs 00-07, 09, 10
        ScanDataset(tmp_path, sequences="train")
    with _raises(InputError, match="expected a split name"):
        ScanDataset(tmp_path, sequences="training")


def test_sequence_dataset_relative_poses(tmp_path, rng):
    lidar_poses = _make_root(tmp_path, rng, {"00": 6, "01": 3})
    dataset = SequenceDataset(tmp_path, num_frames=3, stride=2)  # span 5: 2 windows in 00, none in 01
    assert dataset.windows == [("00", 0), ("00", 1)]
    item = dataset[1]
    assert item["seq"] == "00" and item["frames"] == ["000001", "000003", "000005"]
    assert [len(p) for p in item["points"]] == [21, 23, 25]
    assert item["labels"][0].shape == (21,) and item["labels"][1] is None
    expected = np.linalg.inv(lidar_poses["00"][1]) @ lidar_poses["00"][[1, 3, 5]]  # T_0^-1 T_i
    assert item["poses"].shape == (3, 4, 4)
    np.testing.assert_allclose(item["poses"], expected, atol=1e-9)
    np.testing.assert_allclose(item["poses"][0], np.eye(4), atol=1e-12)
    assert len(SequenceDataset(tmp_path, num_frames=2)) == 5 + 2
    assert len(SequenceDataset(tmp_path, num_frames=1)) == 9


def test_sequence_dataset_bad_input(tmp_path, rng):
    _make_root(tmp_path, rng, {"00": 3})
    with pytest.raises(InputError, match="needs"):
        SequenceDataset(tmp_path, num_frames=4)
    with pytest.raises(InputError, match="num_frames and stride must be >= 1"):
        SequenceDataset(tmp_path, num_frames=2, stride=0)
    (tmp_path / "sequences" / "00" / "poses.txt").unlink()
    with pytest.raises(InputError, match=r"poses.txt: not found") as info:
        SequenceDataset(tmp_path, num_frames=2)
    assert str(tmp_path / "sequences" / "00" / "poses.txt") in str(info.value)
    item = SequenceDataset(tmp_path, num_frames=2, with_poses=False)[0]
    assert item["poses"] is None and len(item["points"]) == 2
    write_poses(tmp_path / "sequences" / "00" / "poses.txt", np.stack([np.eye(4)] * 2))  # 2 poses, 3 frames
    with pytest.raises(InputError, match="2 poses but frame 000002"):
        SequenceDataset(tmp_path, num_frames=2)


def test_detect_format_by_the_folders_of_a_root(tmp_path):
    (tmp_path / "kitti" / "sequences").mkdir(parents=True)
    (tmp_path / "nusc" / "v1.0-mini").mkdir(parents=True)
    (tmp_path / "both" / "sequences").mkdir(parents=True)
    (tmp_path / "both" / "samples" / "LIDAR_TOP").mkdir(parents=True)
    (tmp_path / "neither" / "velodyne").mkdir(parents=True)
    assert detect_format(tmp_path / "kitti") == "semantickitti" and detect_format(tmp_path / "nusc") == "nuscenes"
    with pytest.raises(InputError, match="both: holds both sequences/ .*; name the layout with --format"):
        detect_format(tmp_path / "both")
    looked = (
        r"neither: no dataset layout: looked for sequences/ \(SemanticKITTI\) and a v1.0-\* table folder or samples"
    )
    with pytest.raises(InputError, match=looked):
        detect_format(tmp_path / "neither")
    with pytest.raises(InputError, match="missing: folder not found; expected a dataset root"):
        detect_format(tmp_path / "missing")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="file: is a file; expected a dataset root"):
        detect_format(tmp_path / "file")


# ------------------------------------------------------------------------------------------------------------
# real seq 00 sample (frames 0-5, labels for 0-2)


def test_detect_format_of_the_real_roots(real_root: Path):
    assert detect_format(real_root / "semantickitti") == "semantickitti"
    assert detect_format(real_root / "semantickitti_mmdet3d_tests") == "semantickitti"
    nuscenes = [real_root / name for name in ("nuscenes_mmdet3d_demo", "nuscenes_mmdet3d_tests")]
    if not all(root.is_dir() for root in nuscenes):
        pytest.skip(f"real nuScenes samples not found under {real_root}")
    assert [detect_format(root) for root in nuscenes] == ["nuscenes", "nuscenes"]  # samples/LIDAR_TOP/, no tables
    with pytest.raises(InputError, match="no dataset layout"):
        detect_format(real_root)  # the folder of the datasets is none itself


def test_real_scan_dataset(kitti_root: Path):
    dataset = ScanDataset(kitti_root, sequences=["00"])
    assert [frame for _, frame in dataset.entries] == [f"{i:06d}" for i in range(6)]
    assert len(ScanDataset(kitti_root, labeled_only=True)) == 3
    for index, count in enumerate([124_668, 124_605, 124_478]):
        item = dataset[index]
        assert item["points"].shape == (count, 4) and item["labels"].shape == (count,)
        assert item["labels"].min() >= 0 and item["labels"].max() <= 19
    assert dataset[3]["labels"] is None and dataset[3]["points"].shape == (124_167, 4)


def _median_nn(reference: np.ndarray, query: np.ndarray) -> float:
    reference = reference[np.linalg.norm(reference, axis=1) < 40.0]
    query = query[np.linalg.norm(query, axis=1) < 40.0]
    distances, _ = cKDTree(reference).query(query, k=1)
    return float(np.median(distances))


def test_real_pose_alignment_lowers_nn_distance(kitti_root: Path):
    item = SequenceDataset(kitti_root, num_frames=2, stride=5)[0]  # frames 0 and 5
    assert item["frames"] == ["000000", "000005"]
    xyz0, xyz5 = item["points"][0][:, :3].astype(np.float64), item["points"][1][:, :3].astype(np.float64)
    relative = item["poses"][1]  # T_0^-1 T_5: scan 5 -> scan 0
    aligned = xyz5 @ relative[:3, :3].T + relative[:3, 3]
    raw_median, aligned_median = _median_nn(xyz0, xyz5), _median_nn(xyz0, aligned)
    # SOURCES.md: 0.163 -> 0.069 m
    assert aligned_median < 0.6 * raw_median
    assert raw_median == pytest.approx(0.163, abs=0.01) and aligned_median == pytest.approx(0.069, abs=0.01)
