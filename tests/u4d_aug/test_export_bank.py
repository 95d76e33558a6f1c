"""`u4d export`: a bank in the semantickitti, mmdet3d and pointcept layouts, each read back the way that codebase's
dataset class reads it (mmdetection3d v1.4.0 `SemanticKittiDataset` + `LoadAnnotations3D`, Pointcept
`SemanticKITTIDataset.get_data_list` / `get_data`): every point reads as the ignore label, never as a class."""

from __future__ import annotations

import json
import os
import pickle
import stat
from pathlib import Path

import numpy as np
import pytest

from u4d_aug.bank import BankLayout, read_manifest, sample_digests, verify_samples, write_manifest, write_sample
from u4d_aug.cli import main
from u4d_aug.data.formats import read_calib, read_poses, read_times
from u4d_aug.errors import InputError
from u4d_aug.export_bank import EXPORT_RECORD, INFOS_NAME, POINTCEPT_TRAIN, export_bank, pointcept_sequences

POINTS = (5, 0, 3)  # points of samples 0, 1 (empty: a marker, no .bin), 2

# mmdetection3d configs/_base_/datasets/semantickitti.py: labels_map (raw id -> train id), ignore_index=19
MMDET3D_IGNORE = 19
MMDET3D_LABELS_MAP = {0: 19, 1: 19, 10: 0, 11: 1, 13: 4, 15: 2, 16: 4, 18: 3, 20: 4, 30: 5, 31: 6, 32: 7, 40: 8,
                      44: 9, 48: 10, 49: 11, 50: 12, 51: 13, 52: 19, 60: 8, 70: 14, 71: 15, 72: 16, 80: 17, 81: 18,
                      99: 19, 252: 0, 253: 6, 254: 5, 255: 7, 256: 4, 257: 4, 258: 3, 259: 4}  # fmt: skip
# Pointcept SemanticKITTIDataset.get_learning_map(ignore_index=-1)
POINTCEPT_IGNORE = -1
POINTCEPT_LEARNING_MAP = {**{k: v for k, v in MMDET3D_LABELS_MAP.items() if v != 19},
                          **{k: POINTCEPT_IGNORE for k, v in MMDET3D_LABELS_MAP.items() if v == 19}}  # fmt: skip


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def make_bank(root: Path, frames: int = 1, points: tuple[int, ...] = POINTS) -> BankLayout:
    """A bank of len(points) samples of random points, with the manifest `u4d generate` writes (digests included)."""
    layout = BankLayout(root, frames)
    rng = np.random.default_rng(0)
    samples = []
    for index, count in enumerate(points):
        for frame in range(frames):
            cloud = rng.normal(size=(count, 4)).astype(np.float32)
            write_sample(layout, index, cloud, mask=np.ones((2, 8), dtype=bool), frame=frame)
        samples.append({"index": index, "seed": index, "sha256": sample_digests(layout, index)})
    write_manifest(root, {"mode": "u4d", "frames": frames, "samples": samples, "complete": True})
    return layout


def bank_point_counts(root: Path) -> list[int]:
    """Points of every scan of a bank, in sequence then frame order."""
    return [path.stat().st_size // 16 for path in sorted(root.glob("sequences/*/velodyne/*.bin"))]


def read_label(path: Path) -> np.ndarray:
    """A SemanticKITTI .label: one little-endian uint32 per point, semantic id in the lower 16 bits."""
    return np.fromfile(path, dtype="<u4")


def read_as_mmdet3d(data_root: Path, ann_file: str = INFOS_NAME) -> list[tuple[np.ndarray, np.ndarray]]:
    """(points, train-id mask) of every sample as mmdetection3d v1.4.0 reads them: mmengine BaseDataset loads the
    pkl (metainfo and data_list required), Seg3DDataset.parse_data_info joins data_root + data_prefix ('') + each
    path, LoadPointsFromFile reads float32 rows of num_pts_feats (load_dim=4), LoadAnnotations3D reads the mask as
    int32 (seg_3d_dtype), % 2**16 (seg_offset), PointSegClassMapping applies labels_map."""
    with open(data_root / ann_file, "rb") as f:
        annotations = pickle.load(f)
    assert isinstance(annotations, dict) and set(annotations) == {"metainfo", "data_list"}
    assert annotations["metainfo"] == {"DATASET": "SemanticKITTI"}
    samples = []
    for info in annotations["data_list"]:
        assert set(info) == {"lidar_points", "pts_semantic_mask_path", "sample_id"}
        assert set(info["lidar_points"]) == {"lidar_path", "num_pts_feats"} and isinstance(info["sample_id"], str)
        lidar_path = os.path.join(str(data_root), "", info["lidar_points"]["lidar_path"])
        points = np.fromfile(lidar_path, dtype=np.float32).reshape(-1, info["lidar_points"]["num_pts_feats"])
        mask_path = os.path.join(str(data_root), "", info["pts_semantic_mask_path"])
        mask = np.fromfile(mask_path, dtype=np.int32).astype(np.int64) % 2**16
        mapping = np.full(260, MMDET3D_IGNORE, dtype=np.int64)  # max_label 259, ids not in labels_map -> ignore
        for raw, train in MMDET3D_LABELS_MAP.items():
            mapping[raw] = train
        samples.append((points, mapping[mask]))
    return samples


def read_as_pointcept(data_root: Path, split: str = "train") -> list[tuple[np.ndarray, np.ndarray]]:
    """(points, segment) of every scan as Pointcept's SemanticKITTIDataset reads them: get_data_list lists
    data_root/dataset/sequences/SS/velodyne of each sequence of the split (os.listdir, sorted), get_data reads the
    .bin as float32 (-1, 4) and the label file (velodyne -> labels, .bin -> .label) as int32 & 0xFFFF through
    learning_map (ignore_index -1), or np.zeros (class 0) where no label file exists."""
    split2seq = {"train": [0, 1, 2, 3, 4, 5, 6, 7, 9, 10], "val": [8]}
    data = []
    for seq in split2seq[split]:
        seq_folder = os.path.join(str(data_root), "dataset", "sequences", str(seq).zfill(2))
        for file in sorted(os.listdir(os.path.join(seq_folder, "velodyne"))):
            data_path = os.path.join(seq_folder, "velodyne", file)
            scan = np.fromfile(data_path, dtype=np.float32).reshape(-1, 4)
            label_file = data_path.replace("velodyne", "labels").replace(".bin", ".label")
            if os.path.exists(label_file):
                segment = np.fromfile(label_file, dtype=np.int32).reshape(-1)
                segment = np.vectorize(POINTCEPT_LEARNING_MAP.__getitem__)(segment & 0xFFFF).astype(np.int32)
            else:
                segment = np.zeros(scan.shape[0]).astype(np.int32)
            data.append((scan, segment))
    return data


def files_of(root: Path) -> dict[Path, tuple[bytes, int]]:
    """{file: (bytes, mtime)} of every file under root but its lock."""
    return {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file() and p.name != ".lock"}


# ------------------------------------------------------------------------------------------- semantickitti


def test_semantickitti_in_place_labels_decode_to_unlabeled_one_per_point(tmp_path, umask_022):
    layout = make_bank(tmp_path / "bank")
    record = export_bank(layout.root, "semantickitti")
    for index, count in enumerate(POINTS):
        label = layout.scan_path(index).parent.parent / "labels" / f"{index:06d}.label"
        if count == 0:
            assert not label.exists()  # an empty sample has no scan, hence no labels
            continue
        raw = read_label(label)
        assert len(raw) == count == layout.scan_path(index).stat().st_size // 16
        assert np.all(raw & 0xFFFF == 0) and np.all(raw >> 16 == 0)
        assert stat.S_IMODE(label.stat().st_mode) == 0o644
    manifest = read_manifest(layout.root)
    assert manifest["export"] == record and manifest["placeholder_poses"] is True
    assert record["labels"] == {"kind": "ignore", "semantic": 0, "instance": 0, "files": 2}
    folder = layout.sequence_dir()  # one line per frame number, the empty sample 1 too
    assert len(read_poses(folder / "poses.txt", folder / "calib.txt")) == 3
    np.testing.assert_array_equal(read_times(folder / "times.txt"), [0.0, 0.1, 0.2])


def test_semantickitti_tree_elsewhere_links_into_the_bank_and_writes_nothing_there(tmp_path):
    layout = make_bank(tmp_path / "bank", frames=2)
    before = files_of(layout.root)
    out = tmp_path / "kitti"
    record = export_bank(layout.root, "semantickitti", out)
    assert files_of(layout.root) == before  # nothing written into the bank: no labels, no manifest change
    assert not (layout.root / ".lock").exists()
    for scan in sorted(layout.root.glob("sequences/*/velodyne/*.bin")):
        copy = out / scan.relative_to(layout.root)
        assert copy.read_bytes() == scan.read_bytes() and os.path.samefile(copy, scan)  # a hard link
        assert len(read_label(copy.parent.parent / "labels" / f"{copy.stem}.label")) == scan.stat().st_size // 16
    for sequence in ("00", "02"):  # sample 1 is empty in both frames: no sequence folder with scans
        folder = out / "sequences" / sequence
        assert len(read_poses(folder / "poses.txt", folder / "calib.txt")) == 2 == len(read_times(folder / "times.txt"))
    assert json.loads((out / EXPORT_RECORD).read_text()) == record and record["layout"] == "semantickitti"
    assert record["files"]["linked"] == 4 and record["scans"] == 4


# ------------------------------------------------------------------------------------------- mmdet3d


@pytest.mark.parametrize("where", ["in place", "elsewhere"])
def test_mmdet3d_reads_every_point_as_ignore(tmp_path, umask_022, where):
    layout = make_bank(tmp_path / "bank", frames=2)
    out = None if where == "in place" else tmp_path / "mmdet3d"
    record = export_bank(layout.root, "mmdet3d", out)
    data_root = layout.root if out is None else out
    assert stat.S_IMODE((data_root / INFOS_NAME).stat().st_mode) == 0o644
    samples = read_as_mmdet3d(data_root)
    assert [len(points) for points, _ in samples] == bank_point_counts(layout.root)
    for points, mask in samples:
        assert points.shape[1] == 4 and len(mask) == len(points) and np.all(mask == MMDET3D_IGNORE)
    with open(data_root / INFOS_NAME, "rb") as f:
        data_list = pickle.load(f)["data_list"]
    assert [entry["lidar_points"]["lidar_path"] for entry in data_list] == [
        "sequences/00/velodyne/000000.bin", "sequences/00/velodyne/000001.bin",
        "sequences/02/velodyne/000000.bin", "sequences/02/velodyne/000001.bin",
    ]  # fmt: skip
    assert data_list[3]["pts_semantic_mask_path"] == "sequences/02/labels/000001.label"
    assert [entry["sample_id"] for entry in data_list] == ["00", "01", "20", "21"]  # str(seq) + str(frame) as ints
    assert record["mmdet3d_infos"] == {"path": INFOS_NAME, "samples": 4, "mmdet3d_version": "1.4.0"}


def test_old_flags_map_onto_layouts_with_a_warning(tmp_path, capsys):
    layout = make_bank(tmp_path / "bank")
    assert main(["export", str(layout.root), "--labels", "--mmdet3d-infos"]) == 0
    captured = capsys.readouterr()
    assert "deprecated" in captured.err and "--layout mmdet3d" in captured.err
    assert f"ann_file={INFOS_NAME} (2 samples)" in captured.out
    assert [len(mask) for _, mask in read_as_mmdet3d(layout.root)] == [5, 3]
    assert main(["export", str(layout.root)]) == 0  # no flag: mmdet3d in place, as before (labels and infos)
    assert "deprecated" not in capsys.readouterr().err


# ------------------------------------------------------------------------------------------- pointcept


def test_pointcept_reads_every_point_as_ignore_in_train_sequences(tmp_path):
    layout = make_bank(tmp_path / "bank", frames=2)
    out = tmp_path / "pointcept"
    assert main(["export", str(layout.root), "--layout", "pointcept", "--out", str(out)]) == 0
    data = read_as_pointcept(out)
    assert sorted(len(scan) for scan, _ in data) == sorted(bank_point_counts(layout.root))
    for scan, segment in data:
        assert len(segment) == len(scan) and np.all(segment == POINTCEPT_IGNORE)  # never class 0
    with pytest.raises(FileNotFoundError):
        read_as_pointcept(out, "val")  # the export is a train split only
    record = json.loads((out / EXPORT_RECORD).read_text())
    assert record["pointcept"]["sequences"] == [
        {"bank": "00", "pointcept": "00", "frame_offset": 0, "scans": 2},
        {"bank": "02", "pointcept": "01", "frame_offset": 0, "scans": 2},
    ]
    linked = out / "dataset" / "sequences" / "01" / "velodyne" / "000001.bin"
    assert os.path.samefile(linked, layout.scan_path(2, 1))
    assert not (layout.root / "sequences" / "00" / "labels").exists()  # the labels were written into OUT only


def test_pointcept_without_labels_in_the_bank_would_read_class_0(tmp_path):
    """Why labels matter: a scan without a label file reads as class 0 (car) in Pointcept."""
    layout = make_bank(tmp_path / "bank")
    out = tmp_path / "pointcept"
    export_bank(layout.root, "pointcept", out)
    for label in out.glob("dataset/sequences/*/labels/*.label"):
        label.unlink()
    assert all(np.all(segment == 0) for _, segment in read_as_pointcept(out))


def test_pointcept_mapping_wraps_over_the_ten_train_sequences():
    scans = [Path(f"b/sequences/{i:02d}/velodyne/{f:06d}.bin") for i in range(12) for f in range(2)]
    mapping = pointcept_sequences(scans)
    assert [entry["pointcept"] for entry in mapping] == [*POINTCEPT_TRAIN, "00", "01"]
    assert "08" not in POINTCEPT_TRAIN and mapping[10] == {"bank": "10", "pointcept": "00", "frame_offset": 2,
                                                             "scans": 2}  # fmt: skip


def test_pointcept_needs_an_out_folder_and_refuses_a_foreign_one(tmp_path):
    layout = make_bank(tmp_path / "bank")
    with pytest.raises(InputError, match="give --out DIR"):
        export_bank(layout.root, "pointcept")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="no u4d_export.json"):
        export_bank(layout.root, "pointcept", foreign)
    export_bank(layout.root, "pointcept", tmp_path / "p")
    with pytest.raises(InputError, match="an export of layout pointcept, not mmdet3d"):
        export_bank(layout.root, "mmdet3d", tmp_path / "p")


def test_tree_export_is_idempotent_and_drops_scans_the_bank_no_longer_has(tmp_path):
    layout = make_bank(tmp_path / "bank")
    out = tmp_path / "pointcept"
    export_bank(layout.root, "pointcept", out)
    first = files_of(out)
    export_bank(layout.root, "pointcept", out)
    assert files_of(out) == first  # nothing rewritten
    layout.scan_path(2).unlink()  # the bank lost sample 2 (removed to be generated again)
    export_bank(layout.root, "pointcept", out)
    assert [len(scan) for scan, _ in read_as_pointcept(out)] == [5]


def test_a_bank_being_written_is_not_exported_elsewhere(tmp_path):
    layout = make_bank(tmp_path / "bank")
    lock = {"pid": os.getppid(), "host": os.uname().nodename, "start": None, "started": 0}
    (layout.root / ".lock").write_text(json.dumps(lock))
    with pytest.raises(InputError, match="being written by another run"):
        export_bank(layout.root, "pointcept", tmp_path / "p")
    assert not (tmp_path / "p").exists()


# ------------------------------------------------------------------------------------------- bank integrity


def test_export_keeps_finished_samples_intact_and_is_idempotent(tmp_path):
    layout = make_bank(tmp_path / "bank")
    before = read_manifest(layout.root)
    export_bank(layout.root, "mmdet3d")
    after = read_manifest(layout.root)
    assert after["samples"] == before["samples"]
    assert sorted(verify_samples(layout, after)) == [0, 1, 2]  # what a resumed `u4d generate` checks
    files = files_of(layout.root)
    export_bank(layout.root, "mmdet3d")
    again = files_of(layout.root)
    assert again.keys() == files.keys() and {p: b for p, (b, _) in again.items()} == {
        p: b for p, (b, _) in files.items()
    }
    assert all(again[p][1] == files[p][1] for p in files if p.suffix in (".label", ".json", ".txt"))


def test_stale_label_of_a_rewritten_scan_is_replaced(tmp_path):
    layout = make_bank(tmp_path / "bank")
    export_bank(layout.root, "semantickitti")
    write_sample(layout, 0, np.zeros((7, 4), dtype=np.float32))  # sample 0 generated again, now 7 points
    export_bank(layout.root, "semantickitti")
    assert len(read_label(layout.root / "sequences/00/labels/000000.label")) == 7


def test_not_a_bank_is_one_line_error(tmp_path, capsys):
    folder = tmp_path / "not_a_bank"
    folder.mkdir()
    assert main(["export", str(folder), "--labels"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "not a bank" in err and err.count("\n") == 1
    assert main(["export", str(tmp_path / "missing")]) == 2
    assert not list(folder.iterdir())  # nothing written into a folder that is not a bank


def test_a_removed_sample_takes_its_exported_label_with_it(tmp_path):
    """A damaged sample that `u4d generate` removes to write again leaves no label of the old point count behind."""
    from u4d_aug.bank import remove_sample
    from u4d_aug.data.formats import label_path_for

    layout = make_bank(tmp_path / "bank")
    export_bank(layout.root, "semantickitti")
    label = label_path_for(layout.scan_path(0))
    assert label.is_file()
    remove_sample(layout, 0)
    assert not label.is_file() and not layout.scan_path(0).is_file()
    assert label_path_for(layout.scan_path(2)).is_file()  # other samples keep theirs (sample 1 is empty)


def test_sequence_bank_with_own_poses_keeps_them(tmp_path):
    layout = make_bank(tmp_path / "bank", frames=2, points=(4,))
    from u4d_aug.bank import write_sequence_poses

    moved = np.tile(np.eye(4), (2, 1, 1))
    moved[1, 0, 3] = 2.0  # frame 1 two metres ahead
    write_sequence_poses(layout, 0, moved)
    manifest = read_manifest(layout.root)
    write_manifest(layout.root, {**manifest, "mode": "complete"})
    export_bank(layout.root, "semantickitti")
    folder = layout.sequence_dir(0)
    np.testing.assert_allclose(read_poses(folder / "poses.txt", read_calib(folder / "calib.txt")), moved)
    assert read_manifest(layout.root)["placeholder_poses"] is False and len(read_times(folder / "times.txt")) == 2


# ------------------------------------------------------------------------------------------- u4d generate


def test_generate_writes_labels_by_default_and_infos_when_asked(tmp_path, umask_022):
    from tests.tiny_nets import save_checkpoint

    ckpt = save_checkpoint(tmp_path / "baseline.pt", overrides=("diffusion.stage=baseline",))
    config = tmp_path / "generate.yaml"
    config.write_text(
        f"mode: baseline\nbaseline: {ckpt}\nnum: 2\nsteps: 2\nmean_start_below: null\nbatch_size: 2\ndevice: cpu\n"
    )
    bank = tmp_path / "bank"
    assert main(["generate", str(config), "--out", str(bank), "--mmdet3d-infos", "--no-progress"]) == 0
    scans = sorted(bank.glob("sequences/*/velodyne/*.bin"))
    assert scans  # an untrained net still returns some points
    samples = read_as_mmdet3d(bank)
    assert [len(points) for points, _ in samples] == bank_point_counts(bank)
    assert all(np.all(mask == MMDET3D_IGNORE) for _, mask in samples)
    manifest = read_manifest(bank)
    assert manifest["export"]["labels"]["kind"] == "ignore" and manifest["export"]["mmdet3d_infos"]["samples"] == 2
    assert manifest["complete"] and manifest["config"]["labels"] is True

    bare = tmp_path / "bare"
    assert main(["generate", str(config), "--out", str(bare), "--no-labels", "--no-progress"]) == 0
    assert not list(bare.glob("sequences/*/labels")) and "export" not in read_manifest(bare)
    assert (bare / "sequences" / "00" / "poses.txt").is_file()  # sequence files whatever the labels
    config.write_text(config.read_text() + "labels: false\nmmdet3d_infos: true\n")
    assert main(["generate", str(config), "--out", str(tmp_path / "x"), "--no-progress"]) == 2
