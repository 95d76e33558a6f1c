"""Bank layout (u4d_aug/bank.py): sample paths of single-frame and sequence banks, empty samples, named banks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from u4d_aug.bank import (
    BankLayout,
    has_own_poses,
    named_banks,
    read_manifest,
    record_digests,
    sequence_ids,
    verify_samples,
    write_bank_sequence_files,
    write_manifest,
    write_sample,
    write_sequence_poses,
)
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.formats import read_calib, read_kitti_scan, read_poses, read_times
from u4d_aug.errors import InputError


def test_layout_of_single_frame_and_sequence_banks(tmp_path):
    single, seq = BankLayout(tmp_path), BankLayout(tmp_path, frames=3)
    assert single.scan_path(7) == tmp_path / "sequences" / "00" / "velodyne" / "000007.bin"
    assert seq.scan_path(7, 2) == tmp_path / "sequences" / "07" / "velodyne" / "000002.bin"
    assert seq.stage1_path(12, 0) == tmp_path / "sequences" / "12" / "stage1" / "000000.npy"
    assert seq.poses_path(3) == tmp_path / "sequences" / "03" / "poses.txt"
    with pytest.raises(ValueError, match="frame"):
        single.scan_path(0, 1)
    for frame in range(2):
        write_sample(seq, 0, np.ones((5, 4), np.float32), frame=frame)
    assert not seq.is_done(0)  # frame 2 is missing
    write_sample(seq, 0, np.zeros((0, 4), np.float32), frame=2)
    assert seq.is_done(0) and seq.is_empty(0, 2) and not seq.is_empty(0, 0)


def test_empty_sample_gets_a_marker_not_a_bin(tmp_path):
    layout = BankLayout(tmp_path / "bank")
    write_sample(layout, 0, np.zeros((0, 4), np.float32), mask=np.zeros((4, 8), bool))
    write_sample(layout, 1, np.ones((5, 4), np.float32))
    assert layout.is_done(0) and layout.is_empty(0) and not layout.scan_path(0).exists()
    assert layout.is_done(1) and not layout.is_empty(1) and read_kitti_scan(layout.scan_path(1)).shape == (5, 4)
    assert not np.load(layout.mask_path(0)).any()
    assert ScanDataset(tmp_path / "bank", None).entries == [("00", "000001")]  # readers never meet the empty one


def test_named_banks_and_their_sequences(tmp_path: Path) -> None:
    for seq in ("01", "00"):
        (tmp_path / "a" / "sequences" / seq).mkdir(parents=True)
    (tmp_path / "a" / "sequences" / "notes.txt").write_text("not a sequence")
    (tmp_path / "empty" / "sequences").mkdir(parents=True)
    assert named_banks([f"a={tmp_path / 'a'}", f" b ={tmp_path / 'empty'}"]) == {
        "a": tmp_path / "a",
        "b": tmp_path / "empty",
    }
    assert sequence_ids(tmp_path / "a") == ["00", "01"]
    with pytest.raises(InputError, match="empty/sequences: no sequence folders"):
        sequence_ids(tmp_path / "empty")
    with pytest.raises(InputError, match="expected NAME=DIR"):
        named_banks(["nobank"])
    with pytest.raises(InputError, match="is not a folder"):
        named_banks([f"x={tmp_path}"], flag="--real")
    with pytest.raises(InputError, match="'a' is given twice"):
        named_banks([f"a={tmp_path / 'a'}", f"a={tmp_path / 'empty'}"])


@pytest.mark.parametrize(
    ("manifest", "message"),
    [
        ("[]", r"expected a json object \(a bank.s manifest\), got a list"),
        ('{"samples": 5}', "'samples' must be a list, got int 5"),
        ('{"frames": "two"}', "'frames' must be an integer, got str 'two'"),
        ('{"frames": true}', "'frames' must be an integer"),
        ('{"width": 0}', "'width' must be >= 1, got 0"),
        ('{"export": []}', "'export' must be an object"),
        ('{"samples": [{"index": 0}, {"seed": 1}]}', r"samples\[1\] must be an object with an integer 'index'"),
        ('{"samples": [[0]]}', r"samples\[0\] must be an object"),
        ('{"samples": [{"index": -1}]}', r"samples\[0\] must be an object with an integer 'index' >= 0"),
        (b"\xff\xfe{", "not valid json"),
    ],
)
def test_a_manifest_of_the_wrong_shape_is_one_line_naming_the_field(tmp_path, manifest, message):
    path = tmp_path / "manifest.json"
    path.write_bytes(manifest if isinstance(manifest, bytes) else manifest.encode())
    with pytest.raises(InputError, match=rf"manifest.json: {message}"):
        read_manifest(tmp_path)


def test_a_good_manifest_reads_back(tmp_path):
    record = {"mode": "baseline", "frames": 1, "samples": [{"index": 0, "sha256": {}}], "complete": True}
    write_manifest(tmp_path, record)
    assert read_manifest(tmp_path) == record and read_manifest(tmp_path / "none") is None


def test_samples_without_recorded_digests_are_removed_recorded_ones_kept(tmp_path, caplog):
    layout = BankLayout(tmp_path)
    points = np.ones((3, 4), np.float32)
    for index in range(3):
        write_sample(layout, index, points * index)
    digests = record_digests(layout, 0)
    record_digests(layout, 1)  # recorded in its digest file only (the manifest was not written again)
    manifest = {"samples": [{"index": 0, "sha256": digests}, {"index": 1}, {"index": 2}]}
    with caplog.at_level("WARNING", logger="u4d_aug.bank"):
        verified = verify_samples(layout, manifest)
    assert set(verified) == {0, 1} and verified[0] == digests
    assert "sample 2 has no recorded digests" in caplog.text and not layout.is_done(2)


def test_single_frame_bank_gets_calib_poses_and_times_one_line_per_frame_number(tmp_path):
    layout = BankLayout(tmp_path)
    for index in (0, 2):  # sample 1 empty: no .bin, but its frame number keeps its line
        write_sample(layout, index, np.ones((3, 4), np.float32))
    write_sample(layout, 1, np.zeros((0, 4), np.float32))
    digests = {index: record_digests(layout, index) for index in range(3)}
    write_bank_sequence_files(layout, 3, own_poses=False)
    folder = layout.sequence_dir()
    calib = read_calib(folder / "calib.txt")
    assert sorted(calib) == ["P0", "P1", "P2", "P3", "Tr"] and np.array_equal(calib["Tr"], np.eye(4)[:3])
    np.testing.assert_array_equal(read_poses(folder / "poses.txt", calib), np.tile(np.eye(4), (3, 1, 1)))
    assert (folder / "times.txt").read_text() == "0.0\n0.1\n0.2\n"  # KITTI times.txt: seconds, one per line
    manifest = {"samples": [{"index": i, "sha256": digests[i]} for i in range(3)]}
    assert sorted(verify_samples(layout, manifest)) == [0, 1, 2]  # outside the samples' digests
    mtimes = [(folder / name).stat().st_mtime_ns for name in ("calib.txt", "poses.txt", "times.txt")]
    write_bank_sequence_files(layout, 3, own_poses=False)  # nothing to change: nothing written
    assert [(folder / name).stat().st_mtime_ns for name in ("calib.txt", "poses.txt", "times.txt")] == mtimes
    write_sample(layout, 3, np.ones((3, 4), np.float32))
    write_bank_sequence_files(layout, 4, own_poses=False)  # the bank grew: a line per frame number again
    assert len(read_poses(folder / "poses.txt")) == 4 == len(read_times(folder / "times.txt"))


def test_sequence_bank_keeps_its_own_poses_and_gets_times(tmp_path):
    layout = BankLayout(tmp_path, frames=3)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    write_sequence_poses(layout, 0, poses)
    for frame in range(3):
        write_sample(layout, 0, np.ones((2, 4), np.float32), frame=frame)
    write_sample(layout, 1, np.ones((2, 4), np.float32), frame=0)  # sample 1 unfinished: left alone
    write_bank_sequence_files(layout, 2, own_poses=True)
    folder = layout.sequence_dir(0)
    np.testing.assert_allclose(read_poses(folder / "poses.txt", folder / "calib.txt"), poses)
    np.testing.assert_array_equal(read_times(folder / "times.txt"), [0.0, 0.1, 0.2])
    assert not (layout.sequence_dir(1) / "times.txt").exists()
    assert has_own_poses({"frames": 3, "mode": "complete"}) and has_own_poses({"frames": 3, "motion": "file"})
    assert not has_own_poses({"frames": 1, "mode": "complete"}) and not has_own_poses({"frames": 3, "mode": "u4d"})
