"""`u4d generate` (u4d_aug/generate.py): a bank from tiny untrained checkpoints: layout, manifest, resume,
seed-per-sample, modes."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from tests.tiny_nets import TINY, gen_config
from tests.tiny_worlds import write_posed_world
from u4d_aug.bank import BankLayout, file_sha256, read_manifest
from u4d_aug.config import config_to_dict, load_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.formats import read_kitti_scan, read_poses, read_times, write_kitti_scan
from u4d_aug.data.sensors import get_sensor
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, add_generate_arguments, generate_bank, run_generate
from u4d_aug.io import atomic_save_npy, atomic_torch_save, read_jsonl
from u4d_aug.range_view import project
from u4d_aug.stage import DiffusionTrainConfig, build_net, checkpoint_state


@pytest.fixture(scope="module")
def random_checkpoints(tmp_path_factory) -> dict[str, Path]:
    """Tiny checkpoints with random weights everywhere (the untrained ones predict ε̂ = 0 from zeroed outputs)."""
    root = tmp_path_factory.mktemp("random_ckpt")
    generator = torch.Generator().manual_seed(0)
    paths = {}
    for stage in ("stage1", "stage2", "baseline"):
        cfg = load_config(DiffusionTrainConfig, TINY, [f"diffusion.stage={stage}"])
        net = build_net(cfg)
        with torch.no_grad():
            for p in net.parameters():
                p.copy_(torch.randn(p.shape, generator=generator) * 0.1)
        paths[stage] = root / f"{stage}.pt"
        atomic_torch_save(paths[stage], checkpoint_state(cfg, 0, net, EMA(net)))
    return paths


def test_u4d_bank_layout_and_manifest(untrained_checkpoints, tmp_path):
    bank = tmp_path / "bank"
    manifest = generate_bank(gen_config(untrained_checkpoints, "num=3"), bank, progress=False)
    layout = BankLayout(bank)
    for i in range(3):
        points = read_kitti_scan(layout.scan_path(i))
        assert points.shape[1] == 4 and points.dtype == np.float32 and len(points) > 0
        mask = np.load(layout.mask_path(i))
        assert mask.shape == (16, 64) and mask.dtype == bool
        x0_u = np.load(layout.stage1_path(i))  # stage 1's output: -1 off its predicted mask
        assert x0_u.shape == (2, 16, 64) and x0_u.dtype == np.float16 and np.all(x0_u[:, ~mask] == -1)
        assert not layout.uncertainty_path(i).exists()
    on_disk = read_manifest(bank)
    assert on_disk == manifest and on_disk["complete"] is True
    assert [s["seed"] for s in on_disk["samples"]] == [100, 101, 102]
    assert on_disk["checkpoints"] == {
        "stage1": file_sha256(untrained_checkpoints["stage1"]),
        "stage2": file_sha256(untrained_checkpoints["stage2"]),
    }
    assert len(on_disk["checkpoints"]["stage1"]) == 16 and on_disk["config"]["steps"] == 2


def test_rerun_skips_and_samples_do_not_depend_on_the_split(untrained_checkpoints, tmp_path):
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    generate_bank(gen_config(untrained_checkpoints, "num=3", "mode=baseline"), whole, progress=False)
    generate_bank(gen_config(untrained_checkpoints, "num=1", "mode=baseline"), parts, progress=False)
    layout = BankLayout(parts)
    first = layout.scan_path(0).stat().st_mtime_ns
    generate_bank(gen_config(untrained_checkpoints, "num=3", "mode=baseline"), parts, progress=False)
    assert layout.scan_path(0).stat().st_mtime_ns == first  # skipped, not rewritten
    for i in range(3):
        assert BankLayout(whole).scan_path(i).read_bytes() == layout.scan_path(i).read_bytes()
    layout.scan_path(1).unlink()  # an interrupted sample is generated again, identically
    generate_bank(gen_config(untrained_checkpoints, "num=3", "mode=baseline"), parts, progress=False)
    assert BankLayout(whole).scan_path(1).read_bytes() == layout.scan_path(1).read_bytes()
    with pytest.raises(InputError, match="different"):
        generate_bank(gen_config(untrained_checkpoints, "num=3", "mode=baseline", "steps=3"), parts, progress=False)


def test_manifest_digests_find_a_sample_truncated_by_hand_and_it_is_generated_again(
    untrained_checkpoints, tmp_path, caplog
):
    bank = tmp_path / "bank"
    manifest = generate_bank(gen_config(untrained_checkpoints, "num=2"), bank, progress=False)
    layout = BankLayout(bank)
    digests = manifest["samples"][1]["sha256"]
    assert set(digests) == {"sequences/00/velodyne/000001.bin", "sequences/00/mask/000001.npy",
                            "sequences/00/stage1/000001.npy"}  # fmt: skip
    assert digests["sequences/00/velodyne/000001.bin"] == file_sha256(layout.scan_path(1))
    whole = layout.scan_path(1).read_bytes()
    layout.scan_path(1).write_bytes(whole[: len(whole) // 32 * 16])  # truncated by hand, still whole records
    (layout.scan_path(0).parent / ".000000.bin.abc123.tmp").write_bytes(b"killed write")
    first = layout.scan_path(0).stat().st_mtime_ns
    with caplog.at_level("WARNING", logger="u4d_aug.bank"):
        again = generate_bank(gen_config(untrained_checkpoints, "num=2"), bank, progress=False)
    assert "sample 1 changed since it was written" in caplog.text
    assert layout.scan_path(1).read_bytes() == whole and again["samples"][1]["sha256"] == digests
    assert layout.scan_path(0).stat().st_mtime_ns == first  # the intact sample is kept
    assert not list(bank.rglob("*.tmp")) and not (bank / ".lock").exists()


def test_bank_writes_config_log_and_sequence_files_and_a_rerun_skips_finished_samples(untrained_checkpoints, tmp_path):
    bank = tmp_path / "bank"
    cfg = gen_config(untrained_checkpoints, "num=2", "mode=baseline", "batch_size=1")
    generate_bank(cfg, bank, progress=False)
    assert yaml.safe_load((bank / "config.yaml").read_text()) == config_to_dict(cfg)  # the resolved config
    log = read_jsonl(bank / "log.jsonl")
    assert [record["event"] for record in log] == ["start", "block", "block", "finish"]
    assert [record["samples_done"] for record in log] == [0, 1, 2, 2] and log[-1]["complete"] is True
    assert all(record["seconds"] >= 0 for record in log[1:])
    folder = BankLayout(bank).sequence_dir()
    assert len(read_poses(folder / "poses.txt", folder / "calib.txt")) == 2 == len(read_times(folder / "times.txt"))
    labels = sorted(bank.glob("sequences/00/labels/*.label"))  # labels on by default, all 0 = unlabeled
    assert [p.stem for p in labels] == ["000000", "000001"] and not any(np.fromfile(p, "<u4").any() for p in labels)
    first = BankLayout(bank).scan_path(0).stat().st_mtime_ns
    more = gen_config(untrained_checkpoints, "num=3", "mode=baseline", "batch_size=1")
    again = generate_bank(more, bank, progress=False)  # resumed: samples 0 and 1 are found intact and skipped
    assert BankLayout(bank).scan_path(0).stat().st_mtime_ns == first and again["complete"]
    log = read_jsonl(bank / "log.jsonl")[4:]
    assert [(record["event"], record["samples_done"]) for record in log] == [("start", 2), ("block", 1), ("finish", 3)]
    assert log[1]["block"] == [2, 2] and len(read_poses(folder / "poses.txt")) == 3
    assert yaml.safe_load((bank / "config.yaml").read_text())["num"] == 3


def test_a_sample_written_without_its_digests_is_generated_again(untrained_checkpoints, tmp_path, caplog):
    bank = tmp_path / "bank"
    manifest = generate_bank(gen_config(untrained_checkpoints, "num=3", "mode=baseline"), bank, progress=False)
    layout = BankLayout(bank)
    assert json.loads(layout.digest_path(2).read_text()) == manifest["samples"][2]["sha256"]
    whole = [layout.scan_path(i).read_bytes() for i in range(3)]
    killed = {**manifest, "complete": False, "samples": [dict(entry) for entry in manifest["samples"]]}
    for entry in killed["samples"][1:]:
        del entry["sha256"]  # as a run killed before its manifest recorded samples 1 and 2
    layout.manifest_path.write_text(json.dumps(killed))
    layout.digest_path(1).unlink()  # sample 1: killed between its last file and its digests ...
    layout.scan_path(1).write_bytes(whole[1][:160])  # ... and cut short on disk
    kept = layout.scan_path(2).stat().st_mtime_ns  # sample 2: its digests were recorded, so it is kept
    with caplog.at_level("WARNING", logger="u4d_aug.bank"):
        again = generate_bank(gen_config(untrained_checkpoints, "num=3", "mode=baseline"), bank, progress=False)
    assert "sample 1 has no recorded digests (cut short); generating it again" in caplog.text
    assert [layout.scan_path(i).read_bytes() for i in range(3)] == whole and again["complete"]
    assert layout.scan_path(2).stat().st_mtime_ns == kept and again["samples"] == manifest["samples"]


def real_uncertainty(root: Path, probs_root: Path, frame: str, k: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(m_u (16, 64) bool, entropy map (16, 64)) of scan 00/FRAME, computed apart from the library in float64:
    the pixels of the whole scan's projection whose shown point is among the round(k N) points of highest entropy
    (k = uncertainty.k of configs/u4d/tiny.yaml), and the entropy of the point each pixel shows (NaN where none)."""
    points = read_kitti_scan(root / "sequences" / "00" / "velodyne" / f"{frame}.bin")
    probs = np.load(probs_root / "sequences" / "00" / "probs" / f"{frame}.npy").astype(np.float64)
    h = -(probs * np.log(np.where(probs > 0, probs, 1.0))).sum(axis=1)  # (N,) nats
    count = round(k * len(points))
    order = np.argsort(-h, kind="stable")
    assert h[order[count - 1]] - h[order[count]] > 1e-5  # no near-tie at the cut: float32 picks the same points
    sensor = get_sensor("hdl64")
    winner = project(torch.from_numpy(points), sensor, 16, 64, "linear").winner.numpy()
    selected = np.zeros(len(points), dtype=bool)
    selected[order[:count]] = True
    mask = (winner >= 0) & selected[np.maximum(winner, 0)]
    return mask, np.where(winner >= 0, h[np.maximum(winner, 0)], np.nan)


def test_completion_mode_keeps_real_uncertainty(untrained_checkpoints, tmp_path):
    root, probs_root = tmp_path / "world", tmp_path / "probs"
    rng = np.random.default_rng(0)
    for i in range(2):
        direction = rng.normal(size=(3000, 3))
        direction[:, 2] = np.abs(direction[:, 2]) * -0.2
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        xyz = direction * rng.uniform(3, 50, (3000, 1))
        write_kitti_scan(
            root / "sequences" / "00" / "velodyne" / f"{i:06d}.bin",
            np.concatenate([xyz, rng.uniform(0, 1, (3000, 1))], axis=1).astype(np.float32),
        )
        probs = rng.dirichlet(np.ones(5), 3000).astype(np.float16)
        atomic_save_npy(probs_root / "sequences" / "00" / "probs" / f"{i:06d}.npy", probs)
    cfg = gen_config(untrained_checkpoints, "num=3", "mode=complete", f"data_root={root}", f"probs_root={probs_root}")
    manifest = generate_bank(cfg, tmp_path / "bank", progress=False)
    layout = BankLayout(tmp_path / "bank")
    assert [s["source"] for s in manifest["samples"]] == ["00/000000", "00/000001", "00/000000"]
    mask = np.load(layout.mask_path(0))
    uncertainty = np.load(layout.uncertainty_path(0))
    assert mask.any() and uncertainty.dtype == np.float16 and uncertainty.shape == (16, 64)
    x0_u = np.load(layout.stage1_path(0))  # the real P_u that stage 2 completed
    assert np.all(x0_u[:, ~mask] == -1) and np.all(x0_u[0, mask] > -1)
    assert np.array_equal(mask, np.load(layout.mask_path(2)))  # same source scan, same P_u
    for i in range(2):  # mask and map of samples 0, 1 are those of scans 0, 1 (computed here in float64)
        mask, uncertainty = real_uncertainty(root, probs_root, f"{i:06d}")
        assert np.array_equal(np.load(layout.mask_path(i)), mask), i
        np.testing.assert_allclose(np.load(layout.uncertainty_path(i)), uncertainty, atol=2e-3, rtol=1e-3)  # float16


def test_cli_entry(untrained_checkpoints, tmp_path):
    config = tmp_path / "gen.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "baseline": str(untrained_checkpoints["baseline"]),
                "mode": "baseline",
                "steps": 2,
                "device": "cpu",
                "mean_start_below": None,
            }  # a training checkpoint stores no training mean
        )
    )
    parser = argparse.ArgumentParser()
    add_generate_arguments(parser)
    args = parser.parse_args(
        [str(config), "--out", str(tmp_path / "bank"), "--num", "2", "--seed", "5", "--no-progress"]
    )
    assert run_generate(args) == 0
    manifest = read_manifest(tmp_path / "bank")
    assert [s["seed"] for s in manifest["samples"]] == [5, 6] and manifest["mode"] == "baseline"
    with pytest.raises(InputError, match="stage1"):
        generate_bank(load_config(GenerateConfig, None, ["mode=u4d", "device=cpu"]), tmp_path / "x", progress=False)


# ------------------------------------------------------------------------------------------- sequence banks


def test_u4d_sequence_bank_one_sequence_per_sample(untrained_sequence_checkpoints, tmp_path):
    bank = tmp_path / "bank"
    manifest = generate_bank(gen_config(untrained_sequence_checkpoints, "num=2"), bank, progress=False)
    assert manifest["frames"] == 2 and manifest["complete"] and manifest["empty"] == []
    assert [s["sequence"] for s in manifest["samples"]] == ["00", "01"]
    assert manifest["samples"][1]["files"] == ["sequences/01/velodyne/000000.bin", "sequences/01/velodyne/000001.bin"]
    layout = BankLayout(bank, frames=2)
    for i in range(2):
        for frame in range(2):
            assert len(read_kitti_scan(layout.scan_path(i, frame))) > 0
            mask, x0_u = np.load(layout.mask_path(i, frame)), np.load(layout.stage1_path(i, frame))
            assert mask.shape == (16, 64) and x0_u.shape == (2, 16, 64) and np.all(x0_u[:, ~mask] == -1)
        # generated frames have no poses of their own: identity placeholders, one line per frame, as the manifest says
        np.testing.assert_array_equal(
            read_poses(layout.poses_path(i), layout.calib_path(i)), np.tile(np.eye(4), (2, 1, 1))
        )
        np.testing.assert_array_equal(read_times(layout.sequence_dir(i) / "times.txt"), [0.0, 0.1])
    assert manifest["placeholder_poses"] is True
    assert ScanDataset(bank).entries == [("00", "000000"), ("00", "000001"), ("01", "000000"), ("01", "000001")]
    assert layout.scan_path(0, 0).read_bytes() != layout.scan_path(0, 1).read_bytes()

    again = tmp_path / "again"  # a re-run regenerates an interrupted sample identically
    generate_bank(gen_config(untrained_sequence_checkpoints, "num=2"), again, progress=False)
    BankLayout(again, 2).scan_path(1, 1).unlink()
    generate_bank(gen_config(untrained_sequence_checkpoints, "num=2"), again, progress=False)
    assert BankLayout(again, 2).scan_path(1, 1).read_bytes() == layout.scan_path(1, 1).read_bytes()

    baseline = generate_bank(
        gen_config(untrained_sequence_checkpoints, "num=1", "mode=baseline"), tmp_path / "b", progress=False
    )
    assert baseline["frames"] == 2 and BankLayout(tmp_path / "b", 2).is_done(0)


def test_completion_sequence_bank_keeps_real_poses_for_temporal_metrics(untrained_sequence_checkpoints, tmp_path):
    from u4d_aug.data.formats import read_calib, read_poses
    from u4d_aug.metrics.evaluate import evaluate

    root, probs_root = tmp_path / "world", tmp_path / "probs"
    poses = write_posed_world(root, probs_root)
    cfg = gen_config(
        untrained_sequence_checkpoints, "num=3", "mode=complete", f"data_root={root}", f"probs_root={probs_root}"
    )
    bank = tmp_path / "bank"
    manifest = generate_bank(cfg, bank, progress=False)
    assert [s["source"] for s in manifest["samples"]] == [
        ["00/000000", "00/000001"], ["00/000001", "00/000002"], ["00/000000", "00/000001"]
    ]  # fmt: skip
    layout = BankLayout(bank, frames=2)
    for i, start in enumerate([0, 1, 0]):
        folder = layout.sequence_dir(i)
        np.testing.assert_allclose(read_calib(folder / "calib.txt")["Tr"], np.eye(4)[:3])
        relative = np.linalg.inv(poses[start]) @ poses[start : start + 2]
        np.testing.assert_allclose(read_poses(folder / "poses.txt", read_calib(folder / "calib.txt")), relative)
        for frame in range(2):
            mask, uncertainty = real_uncertainty(root, probs_root, f"{start + frame:06d}")
            written = np.load(layout.mask_path(i, frame))
            assert written.any() and np.array_equal(written, mask)
            np.testing.assert_allclose(np.load(layout.uncertainty_path(i, frame)), uncertainty, atol=2e-3, rtol=1e-3)
    assert np.array_equal(np.load(layout.mask_path(0, 1)), np.load(layout.mask_path(2, 1)))  # same source
    table = evaluate(bank, bank, metrics=("ctc",))["table2"]["bank"]
    assert table["sequences"] == ["00", "01", "02"] and table["ctc_pairs"]["1"] == 3
    assert table["ctc"]["1"] is not None and table["ctc"]["1"] > 0


def test_frames_override_any_length_and_no_mixing_of_layouts(
    untrained_checkpoints, untrained_sequence_checkpoints, tmp_path
):
    """The temporal convs slide along L: a 2-frame generator makes 3-frame sequences, a single-frame one too."""
    longer = generate_bank(
        gen_config(untrained_sequence_checkpoints, "num=1", "frames=3"), tmp_path / "l3", progress=False
    )
    assert longer["frames"] == 3 and BankLayout(tmp_path / "l3", 3).is_done(0)
    independent = generate_bank(
        gen_config(untrained_checkpoints, "num=1", "mode=baseline", "frames=2"), tmp_path / "ind", progress=False
    )
    assert independent["frames"] == 2 and BankLayout(tmp_path / "ind", 2).is_done(0)
    with pytest.raises(InputError, match="2-frame"):
        generate_bank(gen_config(untrained_checkpoints, "num=1", "mode=baseline"), tmp_path / "ind", progress=False)
    with pytest.raises(InputError, match="frames"):
        gen_config(untrained_checkpoints, "frames=0")


def without_digests(entry: dict) -> dict:
    """A manifest sample entry without its file digests."""
    return {key: value for key, value in entry.items() if key != "sha256"}


@pytest.mark.parametrize("mode", ["u4d", "baseline"])
def test_batched_generation_gives_the_one_by_one_scans(random_checkpoints, tmp_path, mode):
    one = generate_bank(gen_config(random_checkpoints, "num=3", f"mode={mode}", "batch_size=1"), tmp_path / "one")
    three = generate_bank(gen_config(random_checkpoints, "num=3", f"mode={mode}", "batch_size=2"), tmp_path / "two")
    # the same listing; the file digests differ by the float rounding of batched sampling
    assert [without_digests(e) for e in one["samples"]] == [without_digests(e) for e in three["samples"]]
    scans = []
    for i in range(3):
        a = read_kitti_scan(BankLayout(tmp_path / "one").scan_path(i))
        b = read_kitti_scan(BankLayout(tmp_path / "two").scan_path(i))
        assert a.shape == b.shape and len(a) > 0
        np.testing.assert_allclose(a, b, atol=1e-3, rtol=1e-3)  # float rounding, amplified by log-depth decoding
        scans.append(a)
    assert scans[0].shape != scans[1].shape or not np.allclose(scans[0], scans[1])  # each sample its own noise
    with pytest.raises(InputError, match="batch_size"):
        gen_config(random_checkpoints, "batch_size=0")
