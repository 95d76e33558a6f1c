"""`u4d export`: all-ignore SemanticKITTI labels and mmdetection3d infos of a bank, read back by their field layout."""

from __future__ import annotations

import os
import pickle
import stat
from pathlib import Path

import numpy as np
import pytest

from u4d_aug.bank import BankLayout, read_manifest, sample_digests, verify_samples, write_manifest, write_sample
from u4d_aug.cli import main
from u4d_aug.export_bank import INFOS_NAME, export_bank, mmdet3d_infos

POINTS = (5, 0, 3)  # points of samples 0, 1 (empty: a marker, no .bin), 2


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def make_bank(root: Path, frames: int = 1) -> BankLayout:
    """A bank of len(POINTS) samples of random points, with the manifest `u4d generate` writes (digests included)."""
    layout = BankLayout(root, frames)
    rng = np.random.default_rng(0)
    samples = []
    for index, count in enumerate(POINTS):
        for frame in range(frames):
            points = rng.normal(size=(count, 4)).astype(np.float32)
            write_sample(layout, index, points, mask=np.ones((2, 8), dtype=bool), frame=frame)
        samples.append({"index": index, "seed": index, "sha256": sample_digests(layout, index)})
    write_manifest(root, {"mode": "u4d", "frames": frames, "samples": samples, "complete": True})
    return layout


def read_label(path: Path) -> np.ndarray:
    """A SemanticKITTI .label: one little-endian uint32 per point, semantic id in the lower 16 bits."""
    return np.fromfile(path, dtype="<u4")


def test_labels_decode_to_unlabeled_one_per_point(tmp_path, umask_022):
    layout = make_bank(tmp_path / "bank")
    export_bank(layout.root, labels=True, infos=False)
    for index, count in enumerate(POINTS):
        label = layout.scan_path(index).parent.parent / "labels" / f"{index:06d}.label"
        if count == 0:
            assert not label.exists()  # an empty sample has no scan, hence no labels
            continue
        raw = read_label(label)
        assert len(raw) == count == layout.scan_path(index).stat().st_size // 16
        assert np.all(raw & 0xFFFF == 0) and np.all(raw >> 16 == 0)
        assert stat.S_IMODE(label.stat().st_mode) == 0o644
    assert read_manifest(layout.root)["export"]["labels"]["files"] == 2


def test_mmdet3d_infos_layout(tmp_path, umask_022):
    layout = make_bank(tmp_path / "bank")
    assert main(["export", str(layout.root), "--labels", "--mmdet3d-infos"]) == 0
    path = layout.root / INFOS_NAME
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    with open(path, "rb") as f:
        infos = pickle.load(f)
    assert infos["metainfo"] == {"dataset": "SemanticKITTI"}
    entries = infos["data_list"]
    assert [entry["sample_idx"] for entry in entries] == ["00000000", "00000002"]
    for entry in entries:
        lidar = entry["lidar_points"]
        assert lidar["num_pts_feats"] == 4
        scan = np.fromfile(layout.root / lidar["lidar_path"], dtype=np.float32).reshape(-1, lidar["num_pts_feats"])
        mask = read_label(layout.root / entry["pts_semantic_mask_path"])
        assert len(mask) == len(scan) and np.all(mask & 0xFFFF == 0)
    record = read_manifest(layout.root)["export"]["mmdet3d_infos"]
    assert record == {"path": INFOS_NAME, "samples": 2, "mmdet3d_version": "1.4.0"}


def test_sequence_bank_and_infos_elsewhere(tmp_path):
    layout = make_bank(tmp_path / "bank", frames=2)
    export_bank(layout.root, labels=True, infos=True, out=tmp_path / "infos")
    with open(tmp_path / "infos" / INFOS_NAME, "rb") as f:
        entries = pickle.load(f)["data_list"]
    assert [entry["lidar_points"]["lidar_path"] for entry in entries] == [
        "sequences/00/velodyne/000000.bin",
        "sequences/00/velodyne/000001.bin",
        "sequences/02/velodyne/000000.bin",
        "sequences/02/velodyne/000001.bin",
    ]
    assert all((layout.root / entry["pts_semantic_mask_path"]).is_file() for entry in entries)


def test_infos_without_labels_name_no_mask(tmp_path):
    layout = make_bank(tmp_path / "bank")
    infos = mmdet3d_infos(layout.root, sorted(layout.root.glob("sequences/*/velodyne/*.bin")))
    assert all("pts_semantic_mask_path" not in entry for entry in infos["data_list"])


def test_export_keeps_finished_samples_intact_and_is_idempotent(tmp_path):
    layout = make_bank(tmp_path / "bank")
    before = read_manifest(layout.root)
    export_bank(layout.root, labels=True, infos=True)
    after = read_manifest(layout.root)
    assert after["samples"] == before["samples"]
    assert sorted(verify_samples(layout, after)) == [0, 1, 2]  # what a resumed `u4d generate` checks
    files = sorted(p for p in layout.root.rglob("*") if p.is_file() and p.name != ".lock")
    contents = {p: p.read_bytes() for p in files}
    mtimes = {p: p.stat().st_mtime_ns for p in files}
    export_bank(layout.root, labels=True, infos=True)
    again = sorted(p for p in layout.root.rglob("*") if p.is_file() and p.name != ".lock")
    assert again == files and {p: p.read_bytes() for p in again} == contents
    assert all(p.stat().st_mtime_ns == mtimes[p] for p in files if p.suffix in (".label", ".json"))


def test_stale_label_of_a_rewritten_scan_is_replaced(tmp_path):
    layout = make_bank(tmp_path / "bank")
    export_bank(layout.root, labels=True, infos=False)
    write_sample(layout, 0, np.zeros((7, 4), dtype=np.float32))  # sample 0 generated again, now 7 points
    export_bank(layout.root, labels=True, infos=False)
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
    export_bank(layout.root, labels=True, infos=False)
    label = label_path_for(layout.scan_path(0))
    assert label.is_file()
    remove_sample(layout, 0)
    assert not label.is_file() and not layout.scan_path(0).is_file()
    assert label_path_for(layout.scan_path(2)).is_file()  # other samples keep theirs (sample 1 is empty)


def test_generate_writes_labels_and_infos_when_asked(tmp_path, umask_022):
    from tests.tiny_nets import save_checkpoint

    ckpt = save_checkpoint(tmp_path / "baseline.pt", overrides=("diffusion.stage=baseline",))
    config = tmp_path / "generate.yaml"
    config.write_text(f"mode: baseline\nbaseline: {ckpt}\nnum: 2\nsteps: 2\nbatch_size: 2\ndevice: cpu\n")
    bank = tmp_path / "bank"
    code = main(["generate", str(config), "--out", str(bank), "--labels", "--mmdet3d-infos", "--no-progress"])
    assert code == 0
    scans = sorted(bank.glob("sequences/*/velodyne/*.bin"))
    assert scans  # an untrained net still returns some points
    for scan in scans:
        label = scan.parent.parent / "labels" / f"{scan.stem}.label"
        assert len(read_label(label)) == scan.stat().st_size // 16 and not read_label(label).any()
    with open(bank / INFOS_NAME, "rb") as f:
        infos = pickle.load(f)
    assert [e["lidar_points"]["lidar_path"] for e in infos["data_list"]] == [
        s.relative_to(bank).as_posix() for s in scans
    ]
    assert all("pts_semantic_mask_path" in e for e in infos["data_list"])
    export = read_manifest(bank)["export"]
    assert export["labels"]["files"] == len(scans) and export["mmdet3d_infos"]["samples"] == len(scans)
    assert read_manifest(bank)["complete"]
