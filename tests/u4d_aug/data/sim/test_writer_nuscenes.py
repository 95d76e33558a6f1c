"""nuScenes end to end on a tiny simulated world: `u4d simulate --format nuscenes` read back by the reader (the same
world as in SemanticKITTI layout), range projection at 32x1024, segmentation with the 16 nuScenes classes (train,
evaluate, predict) and a U4D stage trained on the nuScenes-layout scans at 32x1024."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from segmentation.config import SegTrainConfig
from segmentation.evaluate import evaluate
from segmentation.predict import predict_root
from segmentation.train import train
from tests.tiny_nets import REPO
from u4d_aug.batches import RangeImages
from u4d_aug.cli import main
from u4d_aug.config import load_config
from u4d_aug.data.datasets import NuscenesScanDataset, NuscenesSequenceDataset, SequenceDataset
from u4d_aug.data.formats import (
    read_kitti_label,
    read_kitti_scan,
    read_nuscenes_lidarseg,
    read_nuscenes_scan,
    write_kitti_label,
    write_kitti_scan,
)
from u4d_aug.data.labels import NUSCENES_CLASSES, map_nuscenes, semantickitti_to_nuscenes_raw
from u4d_aug.data.nuscenes import read_nuscenes_index
from u4d_aug.data.sensors import hdl32
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.writer import add_simulate_arguments, lidar_to_ego, run_simulate, simulate
from u4d_aug.errors import InputError
from u4d_aug.range_view import project
from u4d_aug.stage import DiffusionTrainConfig
from u4d_aug.train import train as train_diffusion
from u4d_aug.uncertainty import load_probs, probs_path

CONFIGS = REPO / "configs"
SEED, SCENES, FRAMES = 4, 2, 4  # keyframes every 2nd frame: 2 keyframes and 2 sweeps per scene


def tiny_sim() -> SimConfig:
    return load_config(SimConfig, CONFIGS / "sim" / "tiny.yaml")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("nusc") / "world"
    parser = argparse.ArgumentParser()
    add_simulate_arguments(parser)
    argv = ["--out", str(out), "--format", "nuscenes", "--sequences", str(SCENES), "--frames", str(FRAMES)]
    argv += ["--seed", str(SEED), "--keyframe-every", "2", "--config", str(CONFIGS / "sim" / "tiny.yaml")]
    assert run_simulate(parser.parse_args(argv)) == 0
    return out


def test_written_world_reads_back_as_scenes_of_keyframes_and_sweeps(world: Path) -> None:
    manifest = json.loads((world / "manifest.json").read_text())
    assert (manifest["layout"], manifest["sensor"], manifest["keyframe_every"]) == ("nuscenes", "hdl32", 2)
    index = read_nuscenes_index(world)
    assert list(index.scenes) == ["scene-0000", "scene-0001"]
    for frames in index.scenes.values():
        assert [f.is_key_frame for f in frames] == [True, False, True, False]
        assert np.all(np.diff([f.timestamp for f in frames]) == 100_000)  # 10 Hz in microseconds
        assert all(f.filename.startswith("samples/" if f.is_key_frame else "sweeps/") for f in frames)
        assert [f.lidarseg is not None for f in frames] == [True, False, True, False]
    scans = NuscenesScanDataset(world, labeled_only=True)
    assert len(scans) == 4 and len(NuscenesScanDataset(world, sweeps=True)) == 8
    item = scans[0]
    assert item["points"].dtype == np.float32 and item["labels"].shape == (len(item["points"]),)
    assert set(np.unique(item["labels"])) <= set(range(17)) and (item["labels"] == 10).mean() > 0.2  # road
    raw = read_nuscenes_scan(world / index.scenes["scene-0000"][0].filename, remove_close=0.0)
    assert np.array_equal(raw.points[:, 3] * 255.0, np.round(raw.points[:, 3] * 255.0))  # integer intensities
    elevation = np.degrees(np.arctan2(raw.points[:, 2], np.linalg.norm(raw.points[:, :2], axis=1)))
    medians = [np.median(elevation[raw.ring == r]) for r in np.unique(raw.ring)]
    assert len(medians) == 32 and np.all(np.diff(medians) > 0)  # ring 0 is the bottom ring, as in nuScenes


def test_info_summarises_the_scenes(world: Path, capsys) -> None:
    assert main(["info", str(world), "--format", "nuscenes", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert [s["sequence"] for s in summary["sequences"]] == ["scene-0000", "scene-0001"]
    assert summary["frames"] == summary["labeled_frames"] == 4  # the keyframes
    assert list(summary["class_histogram"]) == [*NUSCENES_CLASSES, "ignore"]
    assert summary["class_histogram"]["driveable_surface"] > 0
    assert main(["info", str(world), "--json"]) == 0  # without --format: the v1.0-trainval/ tables say nuScenes
    assert json.loads(capsys.readouterr().out) == summary and summary["format"] == "nuscenes"
    assert main(["info", str(world), "--format", "nuscenes", "--nuscenes-version", "v1.0-mini"]) == 2
    assert "v1.0-mini: nuScenes table folder not found; it holds v1.0-trainval" in capsys.readouterr().err


def test_the_same_world_in_semantickitti_layout_turned_into_the_nuscenes_lidar_frame(world: Path, tmp_path) -> None:
    kitti = tmp_path / "kitti"
    simulate(kitti, SCENES, FRAMES, SEED, sensor="hdl32", config=tiny_sim(), progress=False)
    scans = NuscenesScanDataset(world, sweeps=True, remove_close=0.0)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90 deg about z: (x, y) -> (-y, x)
    for k, scene in enumerate(["scene-0000", "scene-0001"]):
        for f, token in enumerate(f for seq, f in scans.entries if seq == scene):
            points, labels = scans.load(scene, token)
            reference = read_kitti_scan(kitti / "sequences" / f"{k:02d}" / "velodyne" / f"{f:06d}.bin")
            np.testing.assert_allclose(points[:, :3], reference[:, :3] @ turn.T, atol=1e-5)
            np.testing.assert_allclose(points[:, 3], np.round(reference[:, 3] * 255) / 255, atol=1e-6)
            if f % 2 == 0:
                semantic, _ = read_kitti_label(kitti / "sequences" / f"{k:02d}" / "labels" / f"{f:06d}.label")
                np.testing.assert_array_equal(labels, map_nuscenes(semantickitti_to_nuscenes_raw(semantic)))
            else:
                assert labels is None
    # relative poses: KITTI's (sensor frame) seen in the turned lidar frame
    kitti_poses = SequenceDataset(kitti, FRAMES, ["00"])[0]["poses"]
    nuscenes_poses = NuscenesSequenceDataset(world, FRAMES, ["scene-0000"], sweeps=True)[0]["poses"]
    turn4 = np.eye(4)
    turn4[:3, :3] = turn
    np.testing.assert_allclose(nuscenes_poses, turn4 @ kitti_poses @ turn4.T, atol=1e-6)
    # the ego origin lies sensor_height below the lidar: ego_to_world @ lidar_to_ego = lidar_to_world
    frame = read_nuscenes_index(world).scenes["scene-0000"][0]
    np.testing.assert_allclose(frame.lidar_to_ego, lidar_to_ego(tiny_sim().lidar.sensor_height))
    assert frame.lidar_to_world[2, 3] - frame.ego_to_world[2, 3] == pytest.approx(1.80, abs=0.05)


def test_resume_rewrites_a_missing_sweep_identically_and_refuses_another_layout(world: Path) -> None:
    frame = read_nuscenes_index(world).scenes["scene-0001"][1]
    before = (world / frame.filename).read_bytes()
    tables = (world / "v1.0-trainval" / "sample_data.json").read_bytes()
    (world / frame.filename).unlink()
    summary = simulate(world, SCENES, FRAMES, SEED, config=tiny_sim(), progress=False, layout="nuscenes",
                       keyframe_every=2)  # fmt: skip
    assert (summary["written"], summary["skipped"]) == (1, 7)
    assert (world / frame.filename).read_bytes() == before
    assert (world / "v1.0-trainval" / "sample_data.json").read_bytes() == tables
    with pytest.raises(InputError, match="'layout' differs"):
        simulate(world, SCENES, FRAMES, SEED, sensor="hdl32", config=tiny_sim(), progress=False)


def test_range_projection_at_32x1024_puts_each_ring_in_its_row(world: Path) -> None:
    frame = read_nuscenes_index(world).scenes["scene-0000"][0]
    scan = read_nuscenes_scan(world / frame.filename)
    projection = project(torch.from_numpy(scan.points), hdl32(), 32, 1024, "beam")
    assert projection.depth.shape == (32, 1024)
    inside = (projection.pixel >= 0).numpy()
    assert inside.mean() > 0.99
    rows = projection.pixel.numpy()[inside] // 1024
    assert np.mean(rows == 31 - scan.ring[inside]) > 0.95  # beam rows: top ring first, nuScenes ring 0 at the bottom
    labels = map_nuscenes(read_nuscenes_lidarseg(world / frame.lidarseg)[scan.keep])
    assert set(np.unique(labels[inside])) >= {10, 14}  # driveable surface and manmade project


def test_segmentation_with_the_nuscenes_classes_then_a_u4d_stage_at_32x1024(world: Path, tmp_path: Path) -> None:
    out = tmp_path / "seg"
    cfg = load_config(
        SegTrainConfig,
        CONFIGS / "seg" / "tiny_nuscenes.yaml",
        [f"data.root={world}", f"out_dir={out}", "optim.steps=2", "eval_every=2", "checkpoint_every=2"],
    )
    assert cfg.data.format == "nuscenes" and cfg.model.num_classes == 16
    summary = train(cfg, progress=False)
    assert list(summary["iou"]) == list(NUSCENES_CLASSES) and summary["num_scans"] == 2
    ckpt = torch.load(out / "model.pt", map_location="cpu", weights_only=False)
    assert ckpt["class_names"] == list(NUSCENES_CLASSES) and ckpt["config"]["data"]["format"] == "nuscenes"
    # seg-eval and seg-predict read the root as the checkpoint was trained
    scores = evaluate(out / "model.pt", world, ["scene-0001"])
    assert scores["num_scans"] == 2 and scores["num_points"] > 0 and "driveable_surface" in scores["classes_present"]
    kitti = tmp_path / "kitti"
    points = np.random.default_rng(0).uniform(-10, 10, (100, 4)).astype(np.float32)
    points[:, 3] = 0.5
    write_kitti_scan(kitti / "sequences" / "00" / "velodyne" / "000000.bin", points)
    write_kitti_label(kitti / "sequences" / "00" / "labels" / "000000.label", np.full(100, 40))
    with pytest.raises(InputError, match="a net of 16 classes; the semantickitti scans .* carry 19 train ids"):
        evaluate(out / "model.pt", kitti, None, data_format="semantickitti")
    probs_root = tmp_path / "probs"
    result = predict_root(out / "model.pt", world, probs_root, progress=False)
    assert result["num_scans"] == 4
    scans = NuscenesScanDataset(world)
    for seq, token in scans.entries:
        assert load_probs(probs_path(probs_root, seq, token), len(scans.load_points(seq, token))).shape[1] == 16
    overrides = [f"data.root={world}", f"out_dir={tmp_path / 'bad'}", "model.num_classes=19"]
    with pytest.raises(InputError, match="model.num_classes=19: the nuscenes scans carry 16 train ids"):
        train(load_config(SegTrainConfig, CONFIGS / "seg" / "tiny_nuscenes.yaml", overrides), progress=False)

    # U4D stage 1 on the nuScenes-layout scans and their probabilities, 32x1024 beam rows of the HDL-32E
    u4d = load_config(
        DiffusionTrainConfig,
        CONFIGS / "u4d" / "tiny.yaml",
        [f"data_root={world}", "data_format=nuscenes", "sequences=['0-1']", f"probs_root={probs_root}",
         "sensor=hdl32", "height=32", "width=1024", "row_mode=beam", "diffusion.stage=stage1", "steps=2",
         f"out={tmp_path / 'stage1'}"],
    )  # fmt: skip
    images = RangeImages(u4d)
    assert len(images) == 4 and images.window(0) == ("scene-0000", [scans.entries[0][1]])
    item = images[0]
    assert item["x0"].shape == (2, 32, 1024) and item["m_u"].shape == (1, 32, 1024)
    assert 0 < int(item["m_u"].sum()) < int((item["x0"][0] > -1).sum())  # P_u: a part of the returns
    record = train_diffusion(u4d, progress=False)
    assert record["step"] == 2 and np.isfinite(record["loss"]) and "mask_bce" in record
