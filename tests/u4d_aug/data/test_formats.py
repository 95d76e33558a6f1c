"""SemanticKITTI / nuScenes readers and writers: round trips, bad input, real scans in ../shared/data/real."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from u4d_aug.data.formats import (
    label_path_for,
    load_kitti_frame,
    read_calib,
    read_kitti_label,
    read_kitti_scan,
    read_nuscenes_lidarseg,
    read_nuscenes_scan,
    read_poses,
    read_times,
    write_calib,
    write_kitti_label,
    write_kitti_scan,
    write_nuscenes_lidarseg,
    write_nuscenes_scan,
    write_poses,
    write_times,
)
from u4d_aug.data.labels import (
    NUSCENES_CLASSES,
    NUSCENES_IGNORE,
    SEMANTICKITTI_CLASSES,
    SEMANTICKITTI_IGNORE,
    map_nuscenes,
    map_semantickitti,
)
from u4d_aug.errors import InputError

NUSCENES_DEMO = (
    "nuscenes_mmdet3d_demo/samples/LIDAR_TOP/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
)
NUSCENES_40 = (
    "nuscenes_mmdet3d_tests/samples/LIDAR_TOP/n015-2018-08-02-17-16-37+0800__LIDAR_TOP__1533201470948018.pcd.bin"
)
LIDARSEG_40 = "nuscenes_mmdet3d_tests/lidarseg/v1.0-trainval/5f6c1e0a0c3b444b97e78d2aa3fa34d2_lidarseg.bin"


def _raises_one_line(match: str, func, *args, **kwargs) -> str:
    with pytest.raises(InputError, match=match) as info:
        func(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    return message


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pose = np.eye(4)
    pose[:3, :3] = q * np.sign(np.linalg.det(q))
    pose[:3, 3] = rng.normal(size=3) * 10
    return pose


# ------------------------------------------------------------------------------------------------------------
# round trips


def test_kitti_scan_and_label_round_trip(tmp_path, rng):
    points = rng.normal(size=(100, 4)).astype(np.float32)
    write_kitti_scan(tmp_path / "velodyne" / "000000.bin", points)
    np.testing.assert_array_equal(read_kitti_scan(tmp_path / "velodyne" / "000000.bin"), points)
    semantic = rng.integers(0, 260, size=100).astype(np.uint16)
    instance = rng.integers(0, 65536, size=100).astype(np.uint16)
    label_path = label_path_for(tmp_path / "velodyne" / "000000.bin")
    assert label_path == tmp_path / "labels" / "000000.label"
    write_kitti_label(label_path, semantic, instance)
    assert label_path.stat().st_size == 400
    sem, inst = read_kitti_label(label_path, num_points=100)
    assert sem.dtype == inst.dtype == np.uint16
    np.testing.assert_array_equal(sem, semantic)
    np.testing.assert_array_equal(inst, instance)
    write_kitti_label(label_path, semantic)  # instance defaults to 0
    np.testing.assert_array_equal(read_kitti_label(label_path)[1], 0)
    frame = load_kitti_frame(tmp_path / "velodyne" / "000000.bin", label_path)
    np.testing.assert_array_equal(frame.points, points)
    assert list(tmp_path.rglob("*.tmp")) == []  # atomic writes leave no temp files


def test_label_path_outside_velodyne(tmp_path):
    assert label_path_for(tmp_path / "scans" / "a.bin") == tmp_path / "scans" / "a.label"


def test_calib_poses_times_round_trip(tmp_path, rng):
    calib = {f"P{i}": rng.normal(size=(3, 4)) for i in range(4)}
    calib["Tr"] = _random_pose(rng)[:3]
    write_calib(tmp_path / "calib.txt", calib)
    back = read_calib(tmp_path / "calib.txt")
    assert list(back) == ["P0", "P1", "P2", "P3", "Tr"]
    for key in calib:
        np.testing.assert_array_equal(back[key], calib[key])  # exact: shortest round-trip float text

    lidar_poses = np.stack([_random_pose(rng) for _ in range(5)])
    write_poses(tmp_path / "poses.txt", lidar_poses, calib)
    np.testing.assert_allclose(read_poses(tmp_path / "poses.txt", calib), lidar_poses, atol=1e-12)
    np.testing.assert_allclose(read_poses(tmp_path / "poses.txt", tmp_path / "calib.txt"), lidar_poses, atol=1e-12)
    write_poses(tmp_path / "cam.txt", lidar_poses)  # no calib: written and read back as given
    np.testing.assert_array_equal(read_poses(tmp_path / "cam.txt"), lidar_poses)

    times = np.cumsum(rng.uniform(0.09, 0.11, size=7))
    write_times(tmp_path / "times.txt", times)
    np.testing.assert_array_equal(read_times(tmp_path / "times.txt"), times)


def test_nuscenes_round_trip_and_remove_close(tmp_path, rng):
    points = rng.uniform(-5, 5, size=(50, 4)).astype(np.float32)
    points[:, 3] = rng.integers(0, 256, size=50) / 255.0
    points[:3, :3] = [[0.1, 0.2, 0.0], [0.5, -0.5, 0.5], [0.0, 0.0, 0.99]]  # within 1 m
    ring = rng.integers(0, 32, size=50)
    write_nuscenes_scan(tmp_path / "a.pcd.bin", points, ring)
    assert (tmp_path / "a.pcd.bin").stat().st_size == 50 * 20
    full = read_nuscenes_scan(tmp_path / "a.pcd.bin", remove_close=0.0)
    np.testing.assert_allclose(full.points, points, atol=1e-6)
    np.testing.assert_array_equal(full.ring, ring)
    assert full.keep.all() and full.ring.dtype == np.int64
    near = np.linalg.norm(points[:, :3], axis=1) < 1.0
    scan = read_nuscenes_scan(tmp_path / "a.pcd.bin")
    np.testing.assert_array_equal(scan.keep, ~near)
    np.testing.assert_allclose(scan.points, points[~near], atol=1e-6)
    labels = rng.integers(0, 32, size=50).astype(np.uint8)
    write_nuscenes_lidarseg(tmp_path / "a_lidarseg.bin", labels)
    back = read_nuscenes_lidarseg(tmp_path / "a_lidarseg.bin", num_points=len(scan.keep))
    np.testing.assert_array_equal(back, labels)
    assert len(back[scan.keep]) == len(scan.points)


# ------------------------------------------------------------------------------------------------------------
# bad input: one-line InputError naming the file


def test_bad_kitti_bin_size(tmp_path):
    path = tmp_path / "bad.bin"
    path.write_bytes(b"\0" * 17)
    msg = _raises_one_line("not a multiple of 16", read_kitti_scan, path)
    assert str(path) in msg


def _ray_points(rng: np.random.Generator, num_points: int = 400) -> np.ndarray:
    """(N, 4) float64: points 3-60 m away, intensity in [0, 1], as a KITTI scan holds them."""
    xyz = rng.normal(size=(num_points, 3))
    xyz *= rng.uniform(3, 60, (num_points, 1)) / np.linalg.norm(xyz, axis=1, keepdims=True)
    return np.concatenate([xyz, rng.uniform(0, 1, (num_points, 1))], axis=1)


@pytest.fixture
def fresh_scan_warnings(monkeypatch):
    """Scan warnings are limited per process; each test starts with none given."""
    import u4d_aug.data.formats as formats

    monkeypatch.setattr(formats, "_SCAN_WARNINGS", {})


def test_a_nuscenes_scan_named_bin_is_refused(tmp_path, rng, fresh_scan_warnings):
    points = _ray_points(rng, 400).astype(np.float32)
    write_nuscenes_scan(tmp_path / "scan.pcd.bin", points, rng.integers(0, 32, len(points)))
    (tmp_path / "scan.bin").write_bytes((tmp_path / "scan.pcd.bin").read_bytes())  # 400 x 20 bytes = 500 x 16
    _raises_one_line("like a nuScenes scan, not KITTI's 4; name it \\*.pcd.bin", read_kitti_scan, tmp_path / "scan.bin")


def test_float64_and_out_of_range_intensity_warn(tmp_path, rng, fresh_scan_warnings):
    points = _ray_points(rng)
    points.tofile(tmp_path / "f64.bin")  # float64: 32 bytes a point, a multiple of 16 too
    with pytest.warns(UserWarning, match="f64.bin: its values look like float64"):
        read_kitti_scan(tmp_path / "f64.bin")
    scaled = points * np.array([1, 1, 1, 255])
    write_kitti_scan(tmp_path / "i255.bin", scaled.astype(np.float32))
    with pytest.warns(UserWarning, match="i255.bin: intensity up to 25[0-9.]*, on a 0-255 scale"):
        read_kitti_scan(tmp_path / "i255.bin")
    scaled[0, 3] = 1000.0
    write_kitti_scan(tmp_path / "i1000.bin", scaled.astype(np.float32))
    with pytest.warns(UserWarning, match="outside \\[0, 1\\] and \\[0, 255\\]"):
        read_kitti_scan(tmp_path / "i1000.bin")
    write_kitti_scan(tmp_path / "ok.bin", points.astype(np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(read_kitti_scan(tmp_path / "ok.bin"), points.astype(np.float32))


def test_scan_warnings_stop_after_a_few_files(tmp_path, rng, fresh_scan_warnings):
    scaled = (_ray_points(rng) * np.array([1, 1, 1, 255])).astype(np.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for i in range(6):
            write_kitti_scan(tmp_path / f"{i}.bin", scaled)
            read_kitti_scan(tmp_path / f"{i}.bin")
    messages = [str(w.message) for w in caught]
    assert len(messages) == 3 and messages[-1].endswith("(further files with this problem are not reported)")


def test_bad_nuscenes_bin_size(tmp_path):
    path = tmp_path / "bad.pcd.bin"
    path.write_bytes(b"\0" * 24)
    assert str(path) in _raises_one_line("not a multiple of 20", read_nuscenes_scan, path)


def test_empty_scan(tmp_path):
    (tmp_path / "empty.bin").write_bytes(b"")
    _raises_one_line("empty scan", read_kitti_scan, tmp_path / "empty.bin")
    _raises_one_line("empty scan", load_kitti_frame, tmp_path / "empty.bin")
    (tmp_path / "empty.pcd.bin").write_bytes(b"")
    _raises_one_line("empty scan", read_nuscenes_scan, tmp_path / "empty.pcd.bin")
    with pytest.raises(InputError):
        write_kitti_scan(tmp_path / "x.bin", np.zeros((0, 4)))


def test_missing_file(tmp_path):
    assert str(tmp_path / "nope.bin") in _raises_one_line("not found", read_kitti_scan, tmp_path / "nope.bin")
    _raises_one_line("not found", read_calib, tmp_path / "calib.txt")


def test_label_count_mismatch(tmp_path, rng):
    write_kitti_scan(tmp_path / "velodyne" / "0.bin", rng.normal(size=(10, 4)))
    write_kitti_label(tmp_path / "labels" / "0.label", np.zeros(9, dtype=np.uint16))
    msg = _raises_one_line("9 labels but the scan has 10 points", load_kitti_frame,
                           tmp_path / "velodyne" / "0.bin", tmp_path / "labels" / "0.label")  # fmt: skip
    assert "0.label" in msg
    (tmp_path / "odd.label").write_bytes(b"\0" * 6)
    _raises_one_line("not a multiple of 4", read_kitti_label, tmp_path / "odd.label")
    write_nuscenes_lidarseg(tmp_path / "seg.bin", np.zeros(3, dtype=np.uint8))
    _raises_one_line("3 labels but the scan has 4 points", read_nuscenes_lidarseg, tmp_path / "seg.bin", 4)


def test_nonfinite_points_dropped_with_their_labels(tmp_path, rng):
    points = rng.normal(size=(8, 4)).astype(np.float32)
    points[1, 0] = np.nan
    points[4, 2] = np.inf
    points[6, 3] = -np.inf
    points = np.concatenate([points, [[2e4, 0, 0, 0.5], [0, 0, -3e38, 0.5]]]).astype(np.float32)  # beyond 10 km
    semantic = np.arange(10, dtype=np.uint16) + 10
    write_kitti_scan(tmp_path / "s.bin", points)
    write_kitti_label(tmp_path / "s.label", semantic, semantic + 100)
    with pytest.warns(UserWarning, match=r"dropped 5 of 10 points \(3 with NaN/inf values, 2 beyond 10000 m\)"):
        frame = load_kitti_frame(tmp_path / "s.bin", tmp_path / "s.label")
    keep = [0, 2, 3, 5, 7]
    np.testing.assert_array_equal(frame.points, points[keep])
    assert frame.semantic.tolist() == [10, 12, 13, 15, 17]
    assert frame.instance.tolist() == [110, 112, 113, 115, 117]

    write_kitti_scan(tmp_path / "nan.bin", np.full((3, 4), np.nan))
    with pytest.warns(UserWarning):
        _raises_one_line("all 3 points are NaN/inf", load_kitti_frame, tmp_path / "nan.bin")

    write_nuscenes_scan(tmp_path / "n.pcd.bin", np.where(np.isfinite(points), points, np.nan) + 2, np.arange(10))
    with pytest.warns(UserWarning, match=r"dropped 5 of 10 points \(3 with NaN/inf values, 2 beyond"):
        scan = read_nuscenes_scan(tmp_path / "n.pcd.bin", remove_close=0)
    np.testing.assert_array_equal(np.flatnonzero(scan.keep), keep)
    assert scan.ring.tolist() == keep


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("P0: 1 2 3\n", r"calib.txt:1: expected 12 numbers"),
        ("P0: " + "1 " * 12 + "\nTr: " + "x " * 12 + "\n", r"calib.txt:2: .*non-numeric"),
        ("no colon here\n", r"calib.txt:1: expected 'KEY: 12 numbers'"),
        ("\n\n", r"calib.txt: calib file holds no"),
    ],
)
def test_malformed_calib(tmp_path, text, match):
    (tmp_path / "calib.txt").write_text(text)
    _raises_one_line(match, read_calib, tmp_path / "calib.txt")


def test_malformed_poses_and_times(tmp_path):
    good = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])
    (tmp_path / "poses.txt").write_text(f"{good}\n{good} 5\n")
    _raises_one_line(r"poses.txt:2: expected 12 numbers \(3x4 pose\), got 13", read_poses, tmp_path / "poses.txt")
    (tmp_path / "poses.txt").write_text("")
    _raises_one_line("poses file is empty", read_poses, tmp_path / "poses.txt")
    (tmp_path / "poses.txt").write_text(good + "\n")
    (tmp_path / "calib.txt").write_text("P0: " + good + "\n")
    _raises_one_line("no 'Tr' entry", read_poses, tmp_path / "poses.txt", tmp_path / "calib.txt")
    (tmp_path / "times.txt").write_text("0.0\n0.1 0.2\n")
    _raises_one_line(r"times.txt:2: expected 1 numbers", read_times, tmp_path / "times.txt")


# ------------------------------------------------------------------------------------------------------------
# real scans (../shared/data/real)

FRAME0_RAW_COUNTS = {  # SOURCES.md, labels/000000.label
    0: 2184, 1: 4, 10: 4234, 40: 34228, 44: 3268, 48: 26360, 50: 18268, 51: 370, 52: 1471, 60: 1053,
    70: 27123, 71: 1192, 72: 2964, 80: 532, 81: 102, 99: 1227, 255: 88,
}  # fmt: skip


def test_real_kitti_frames_load(kitti_root: Path):
    velodyne = kitti_root / "sequences" / "00" / "velodyne"
    for name, count in [("000000", 124_668), ("000001", 124_605), ("000002", 124_478)]:
        frame = load_kitti_frame(velodyne / f"{name}.bin", label_path_for(velodyne / f"{name}.bin"))
        assert frame.points.shape == (count, 4) and frame.points.dtype == np.float32
        assert frame.semantic.shape == frame.instance.shape == (count,)
        assert frame.points[:, 3].min() >= 0.0 and frame.points[:, 3].max() <= 1.0
        assert len(np.unique(frame.instance[frame.instance > 0])) == 14  # SOURCES.md: 14 distinct instance ids


def test_real_kitti_frame0_class_counts(kitti_root: Path):
    scan = kitti_root / "sequences" / "00" / "velodyne" / "000000.bin"
    frame = load_kitti_frame(scan, label_path_for(scan))
    raw_ids, raw_counts = np.unique(frame.semantic, return_counts=True)
    assert dict(zip(raw_ids.tolist(), raw_counts.tolist(), strict=True)) == FRAME0_RAW_COUNTS
    # expected after the learning map, written out by hand from the protocol table
    expected = {
        "car": 4234, "motorcyclist": 88, "road": 34228 + 1053, "parking": 3268, "sidewalk": 26360,
        "building": 18268, "fence": 370, "vegetation": 27123, "trunk": 1192, "terrain": 2964, "pole": 532,
        "traffic-sign": 102,
    }  # fmt: skip
    counts = np.bincount(map_semantickitti(frame.semantic), minlength=SEMANTICKITTI_IGNORE + 1)
    got = {name: int(counts[i]) for i, name in enumerate(SEMANTICKITTI_CLASSES) if counts[i]}
    assert got == expected
    assert counts[SEMANTICKITTI_IGNORE] == 2184 + 4 + 1471 + 1227  # unlabeled, outlier, other-structure, other-object
    assert counts.sum() == 124_668


def test_real_mmdet3d_subset(real_root: Path):
    scan = real_root / "semantickitti_mmdet3d_tests" / "sequences" / "00" / "velodyne" / "000000.bin"
    frame = load_kitti_frame(scan, label_path_for(scan))
    raw_ids, raw_counts = np.unique(frame.semantic, return_counts=True)
    assert dict(zip(raw_ids.tolist(), raw_counts.tolist(), strict=True)) == {
        0: 2,
        50: 25,
        52: 1,
        70: 17,
        71: 3,
        80: 2,
    }


def test_real_calib_poses_times(kitti_root: Path, tmp_path):
    folder = kitti_root / "sequences" / "00"
    calib = read_calib(folder / "calib.txt")
    assert sorted(calib) == ["P0", "P1", "P2", "P3", "Tr"]
    assert calib["P0"][0, 0] == pytest.approx(718.856)
    camera = read_poses(folder / "poses.txt")
    lidar = read_poses(folder / "poses.txt", calib)
    assert camera.shape == lidar.shape == (4541, 4, 4)
    np.testing.assert_allclose(lidar[0], np.eye(4), atol=1e-6)
    # ego motion 0 -> 5 is about 3.55 m (SOURCES.md), forward along LiDAR +x
    assert np.linalg.norm(lidar[5, :3, 3]) == pytest.approx(3.55, abs=0.02)
    assert lidar[5, 0, 3] > 3.4
    times = read_times(folder / "times.txt")
    assert times.shape == (4541,) and np.median(np.diff(times)) == pytest.approx(0.1037, abs=1e-3)
    # writers invert the readers on the real files
    write_calib(tmp_path / "calib.txt", calib)
    assert all(np.array_equal(read_calib(tmp_path / "calib.txt")[k], calib[k]) for k in calib)
    write_poses(tmp_path / "poses.txt", lidar, calib)
    np.testing.assert_allclose(read_poses(tmp_path / "poses.txt"), camera, atol=1e-9)
    np.testing.assert_allclose(read_poses(tmp_path / "poses.txt", calib), lidar, atol=1e-9)


def test_real_nuscenes_demo_scan(real_root: Path):
    raw = read_nuscenes_scan(real_root / NUSCENES_DEMO, remove_close=0.0)
    assert raw.points.shape == (34_688, 4) and raw.keep.all()
    assert raw.points[:, 3].max() == pytest.approx(1.0) and raw.points[:, 3].min() >= 0.0
    assert raw.ring.min() == 0 and raw.ring.max() == 31 and len(np.unique(raw.ring)) == 32
    scan = read_nuscenes_scan(real_root / NUSCENES_DEMO)  # remove_close=1.0 by default
    assert int((~scan.keep).sum()) == 8_029  # SOURCES.md: 8,029 ego returns within 1 m
    assert scan.points.shape == (34_688 - 8_029, 4) and len(scan.ring) == len(scan.points)
    assert np.linalg.norm(scan.points[:, :3], axis=1).min() >= 1.0


def test_real_nuscenes_lidarseg_40(real_root: Path):
    scan = read_nuscenes_scan(real_root / NUSCENES_40, remove_close=0.0)
    raw = read_nuscenes_lidarseg(real_root / LIDARSEG_40, num_points=len(scan.keep))
    assert raw.dtype == np.uint8 and raw.shape == (40,)
    ids, counts = np.unique(raw, return_counts=True)
    assert dict(zip(ids.tolist(), counts.tolist(), strict=True)) == {
        17: 2,
        24: 15,
        27: 1,
        28: 12,
        30: 1,
        31: 9,
    }
    train = map_nuscenes(raw)
    counts = np.bincount(train, minlength=NUSCENES_IGNORE + 1)
    got = {([*NUSCENES_CLASSES, "ignore"])[i]: int(c) for i, c in enumerate(counts) if c}
    assert got == {
        "car": 2,
        "driveable_surface": 15,
        "terrain": 1,
        "manmade": 12,
        "vegetation": 1,
        "ignore": 9,
    }
    near = read_nuscenes_scan(real_root / NUSCENES_40)  # labels filter the same way as points
    assert len(raw[near.keep]) == len(near.points)
