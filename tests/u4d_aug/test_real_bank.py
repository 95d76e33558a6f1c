"""`u4d bank-real`: a bank of real scans of unused places, projected as generated scans are, and its split check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.tiny_nets import save_checkpoint
from tests.tiny_worlds import write_toy_root
from u4d_aug.bank import read_manifest
from u4d_aug.cli import main
from u4d_aug.data.datasets import ScanDataset, expand_sequences
from u4d_aug.data.formats import read_kitti_scan, read_poses, read_times
from u4d_aug.data.sensors import get_sensor
from u4d_aug.errors import InputError
from u4d_aug.io import read_jsonl
from u4d_aug.range_view import project
from u4d_aug.real_bank import check_disjoint, check_real_bank, projected_points, split_overlap, write_real_bank

HDL64 = {"sensor": "hdl64", "height": 64, "width": 1024, "row_mode": "beam"}


@pytest.fixture(scope="module")
def places(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A toy root of five places: 00-02 stand for the splits, 03-04 for the unused places."""
    return write_toy_root(tmp_path_factory.mktemp("places"), ("00", "01", "02", "03", "04"), frames=2)


def test_projected_scans_hold_one_point_per_occupied_pixel_at_its_depth(kitti_root: Path):
    scan = read_kitti_scan(kitti_root / "sequences" / "00" / "velodyne" / "000000.bin")
    out = projected_points(scan, HDL64)
    sensor = get_sensor("hdl64")
    before = project(scan, sensor, 64, 1024, "beam")
    assert len(out) == int(before.mask.sum()) < len(scan)  # one return per occupied pixel of 64 x 1024
    again = project(out, sensor, 64, 1024, "beam")
    # each point lands back on its pixel, with its depth (the encoding rounds to float precision)
    assert np.array_equal(again.mask.numpy(), before.mask.numpy())
    np.testing.assert_allclose(again.depth[again.mask].numpy(), before.depth[before.mask].numpy(), rtol=1e-3)


def test_bank_holds_every_scan_of_the_places_with_a_manifest_and_resumes(places: Path, tmp_path: Path):
    bank = tmp_path / "real"
    manifest = write_real_bank(places, ["03-04"], bank, HDL64)
    assert manifest["complete"] and manifest["mode"] == "real"
    assert manifest["source"]["sequences"] == ["03", "04"]
    assert [s["source"] for s in manifest["samples"]] == [
        f"sequences/{seq}/velodyne/{frame:06d}.bin" for seq in ("03", "04") for frame in range(2)
    ]
    assert len(ScanDataset(bank, None)) == 4  # readable as any bank
    first = read_kitti_scan(bank / "sequences" / "00" / "velodyne" / "000000.bin")
    source = read_kitti_scan(places / "sequences" / "03" / "velodyne" / "000000.bin")
    np.testing.assert_array_equal(first, projected_points(source, HDL64))
    # a changed scan is written again on resume; the others are kept
    target = bank / "sequences" / "00" / "velodyne" / "000001.bin"
    target.write_bytes(np.zeros((3, 4), np.float32).tobytes())
    again = write_real_bank(places, ["03-04"], bank, HDL64)
    assert again["samples"] == manifest["samples"]
    # another projection into the same folder is refused, naming the manifest
    with pytest.raises(InputError, match="manifest.json: a bank of other scans or another projection"):
        write_real_bank(places, ["03-04"], bank, None)


def test_bank_has_labels_sequence_files_config_and_log(places: Path, tmp_path: Path):
    bank = tmp_path / "real"
    manifest = write_real_bank(places, ["03-04"], bank, None)
    scans = sorted(bank.glob("sequences/00/velodyne/*.bin"))
    for scan in scans:  # all-ignore labels, one per point: the bank is read as unlabeled, never as class 0
        label = np.fromfile(scan.parent.parent / "labels" / f"{scan.stem}.label", dtype="<u4")
        assert len(label) == scan.stat().st_size // 16 and not label.any()
    assert manifest["export"]["labels"] == {"kind": "ignore", "semantic": 0, "instance": 0, "files": 4}
    folder = bank / "sequences" / "00"
    assert len(read_poses(folder / "poses.txt", folder / "calib.txt")) == 4 == len(read_times(folder / "times.txt"))
    assert read_manifest(bank)["placeholder_poses"] is True
    assert yaml.safe_load((bank / "config.yaml").read_text())["sequences"] == ["03-04"]
    log = read_jsonl(bank / "log.jsonl")
    assert [record["event"] for record in log] == ["start", "finish"] and log[-1]["samples_done"] == 4
    again = write_real_bank(places, ["03-04"], bank, None)  # resumed: every sample intact, labels kept
    assert again["samples"] == manifest["samples"] and read_jsonl(bank / "log.jsonl")[2]["samples_done"] == 4
    bare = write_real_bank(places, ["04"], tmp_path / "bare", None, labels=False)
    assert "export" not in bare and not (tmp_path / "bare" / "sequences" / "00" / "labels").exists()


def test_raw_bank_copies_the_scans(places: Path, tmp_path: Path):
    manifest = write_real_bank(places, ["04"], tmp_path / "raw", None, max_scans=1)
    assert manifest["projection"] is None and len(manifest["samples"]) == 1
    np.testing.assert_array_equal(
        read_kitti_scan(tmp_path / "raw" / "sequences" / "00" / "velodyne" / "000000.bin"),
        read_kitti_scan(places / "sequences" / "04" / "velodyne" / "000000.bin"),
    )


def test_split_check_names_the_split_and_the_shared_places():
    splits = {"data.train_sequences": ["00-87"], "data.val_sequences": ["88-99"]}
    assert split_overlap(expand_sequences(["100-163"]), splits) == {}
    assert split_overlap(expand_sequences(["95-101"]), splits) == {"data.val_sequences": ["95", "96", "97", "98", "99"]}
    check_disjoint("banks/real", expand_sequences(["100-163"]), splits)
    with pytest.raises(InputError, match=r"banks/real: .* also in data.train_sequences: 87 \(1 places\)"):
        check_disjoint("banks/real", ["87", "100"], splits)


def test_a_bank_from_split_places_is_refused_by_the_experiment_check(places: Path, tmp_path: Path):
    overlapping = tmp_path / "overlap"
    write_real_bank(places, ["02-03"], overlapping, None, max_scans=1)
    with pytest.raises(InputError, match=r"also in data.val_sequences: 02"):
        check_real_bank(overlapping, places, {"data.train_sequences": ["00-01"], "data.val_sequences": ["02"]})
    check_real_bank(overlapping, places, {"data.train_sequences": ["00-01"]})  # 02-03 are in no split here
    check_real_bank(overlapping, tmp_path, {"data.train_sequences": ["00-03"]})  # another root: other places


def test_a_generator_trained_on_the_places_is_refused(places: Path, tmp_path: Path):
    run = save_checkpoint(tmp_path / "gen.pt", overrides=(f"data_root={places}", "sequences=['03']"))
    with pytest.raises(InputError, match=r"also in generator .*gen.pt: 03"):
        write_real_bank(places, ["03-04"], tmp_path / "bank", HDL64, generators=[run])
    assert not (tmp_path / "bank").exists()  # refused before anything is written
    manifest = write_real_bank(places, ["04"], tmp_path / "bank", HDL64, generators=[run])
    assert len(manifest["samples"]) == 2


def test_the_command_writes_the_bank(places: Path, tmp_path: Path, capsys):
    out = tmp_path / "cli"
    assert main(["bank-real", str(places), "--sequences", "03", "--out", str(out), "--width", "512"]) == 0
    assert "2 real scans of 1 places (03-03) through the 64x512 range image" in capsys.readouterr().out
    assert read_manifest(out)["projection"]["width"] == 512
    assert main(["bank-real", str(places), "--sequences", "09", "--out", str(out)]) == 2
    assert "09" in capsys.readouterr().err
