"""`u4d train-diffusion`: a few steps of each stage on tiny synthetic scans, checkpoints, log, resume."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import torch

from u4d_aug.config import load_config
from u4d_aug.data.formats import write_kitti_scan
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_save_npy, read_jsonl
from u4d_aug.train import (
    DiffusionTrainConfig,
    add_train_diffusion_arguments,
    run_train_diffusion,
    split_stage_override,
    train,
)

TINY = Path(__file__).resolve().parents[1] / "configs" / "u4d" / "tiny.yaml"


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def write_tiny_world(root: Path, probs_root: Path, num_scans: int = 3, num_points: int = 4000) -> None:
    """Scans of points on random rays within HDL-64's vertical FOV, 3-60 m, plus random class probabilities."""
    rng = np.random.default_rng(0)
    for i in range(num_scans):
        elevation = np.deg2rad(rng.uniform(-24.0, 2.0, num_points))
        azimuth = rng.uniform(-np.pi, np.pi, num_points)
        depth = rng.uniform(3.0, 60.0, num_points)
        xyz = np.stack(
            [
                depth * np.cos(elevation) * np.cos(azimuth),
                depth * np.cos(elevation) * np.sin(azimuth),
                depth * np.sin(elevation),
            ],
            axis=1,
        )
        points = np.concatenate([xyz, rng.uniform(0, 1, (num_points, 1))], axis=1).astype(np.float32)
        write_kitti_scan(root / "sequences" / "00" / "velodyne" / f"{i:06d}.bin", points)
        logits = rng.normal(size=(num_points, 5)) * 2
        probs = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
        atomic_save_npy(probs_root / "sequences" / "00" / "probs" / f"{i:06d}.npy", probs.astype(np.float16))


@pytest.fixture
def tiny_world(tmp_path: Path) -> tuple[Path, Path]:
    root, probs_root = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(root, probs_root)
    return root, probs_root


def tiny_config(world: tuple[Path, Path], out: Path, stage: str, *extra: str) -> DiffusionTrainConfig:
    overrides = [
        f"data_root={world[0]}",
        f"probs_root={world[1]}",
        f"out={out}",
        *split_stage_override([f"stage={stage}"]),
        *extra,
    ]
    return load_config(DiffusionTrainConfig, TINY, overrides)


@pytest.mark.parametrize("stage", ["stage1", "stage2", "baseline"])
def test_each_stage_trains_and_writes_checkpoint_and_log(tiny_world, tmp_path, stage):
    out = tmp_path / f"run_{stage}"
    cfg = tiny_config(tiny_world, out, stage)
    record = train(cfg, progress=False)
    assert record["step"] == 4 and np.isfinite(record["loss"])
    assert ("mask_bce" in record) == (stage == "stage1")
    log = read_jsonl(out / "log.jsonl")
    assert [r["step"] for r in log] == [2, 4]
    checkpoints = sorted((out / "checkpoints").glob("step_*.pt"))
    assert [c.name for c in checkpoints] == ["step_0000002.pt", "step_0000004.pt"]
    ckpt = torch.load(checkpoints[-1], map_location="cpu", weights_only=False)
    assert ckpt["step"] == 4 and ckpt["config"]["diffusion"]["stage"] == stage
    assert {"model", "ema", "optimizer", "rng"} <= set(ckpt)
    assert ckpt["config"]["net"]["mask_head"] == (stage == "stage1")
    assert ckpt["config"]["net"]["cond_channels"] == (3 if stage == "stage2" else 0)
    assert (out / "config.yaml").is_file()


def test_resume_continues_to_the_same_weights(tiny_world, tmp_path):
    full = tiny_config(tiny_world, tmp_path / "full", "stage2")
    train(full, progress=False)
    part = tiny_config(tiny_world, tmp_path / "part", "stage2", "steps=2")
    train(part, progress=False)
    with pytest.raises(InputError, match="--resume"):
        train(tiny_config(tiny_world, tmp_path / "part", "stage2"), progress=False)
    record = train(tiny_config(tiny_world, tmp_path / "part", "stage2"), resume="last", progress=False)
    assert record["step"] == 4
    assert [r["step"] for r in read_jsonl(tmp_path / "part" / "log.jsonl")] == [2, 4]
    a = torch.load(tmp_path / "full" / "checkpoints" / "step_0000004.pt", weights_only=False)
    b = torch.load(tmp_path / "part" / "checkpoints" / "step_0000004.pt", weights_only=False)
    for name, value in a["model"].items():
        torch.testing.assert_close(b["model"][name], value)


def test_cli_entry_with_short_stage_override_and_sample_png(tiny_world, tmp_path):
    parser = argparse.ArgumentParser()
    add_train_diffusion_arguments(parser)
    out = tmp_path / "cli"
    args = parser.parse_args(
        [str(TINY), "stage=stage1", f"data_root={tiny_world[0]}", f"probs_root={tiny_world[1]}",
         "steps=2", "sample_every=2", "--out", str(out), "--no-progress"]
    )  # fmt: skip
    assert run_train_diffusion(args) == 0
    assert (out / "samples" / "step_0000002.png").is_file()
    assert (out / "checkpoints" / "step_0000002.pt").is_file()


def test_wall_clock_budget_stops_with_a_checkpoint(tiny_world, tmp_path):
    out = tmp_path / "budget"
    record = train(tiny_config(tiny_world, out, "baseline", "steps=50", "max_minutes=1e-9"), progress=False)
    assert record["step"] == 1  # the budget is used after the first step: logged and checkpointed there
    assert [c.name for c in (out / "checkpoints").glob("step_*.pt")] == ["step_0000001.pt"]
    ckpt = torch.load(out / "checkpoints" / "step_0000001.pt", weights_only=False)
    assert ckpt["elapsed"] > 0 and ckpt["config"]["max_minutes"] == 1e-9


def test_u4d_cli_dispatches_train_diffusion(tiny_world, tmp_path):
    from u4d_aug.cli import main

    out = tmp_path / "via_cli"
    argv = ["train-diffusion", str(TINY), "stage=baseline", f"data_root={tiny_world[0]}", "steps=2"]
    assert main([*argv, "--out", str(out), "--no-progress"]) == 0
    assert (out / "checkpoints" / "step_0000002.pt").is_file()
    assert main(["train-diffusion", str(TINY), "stage=stage3", "--out", str(tmp_path / "bad")]) == 2


def test_stage_needs_probabilities(tiny_world, tmp_path):
    with pytest.raises(InputError, match="probs"):
        train(tiny_config(tiny_world, tmp_path / "x", "stage1", "probs_root=''"), progress=False)


@pytest.mark.slow
def test_stage2_overfits_one_scan(tmp_path):
    """Stage 2 trained on one scan completes that scan's x0_u far closer to it than the untrained net (~25 s)."""
    from u4d_aug.pipeline import complete, load_generator
    from u4d_aug.train import RangeImages, build_net

    world = (tmp_path / "world", tmp_path / "probs")
    write_tiny_world(*world, num_scans=1)
    cfg = tiny_config(
        world, tmp_path / "overfit", "stage2",
        "steps=200", "checkpoint_every=1000", "log_every=50", "optim.lr=0.003", "ema_decay=0.0", "batch_size=4",
        "diffusion.min_snr_gamma=null",
    )  # fmt: skip
    train(cfg, progress=False)
    item = RangeImages(cfg)[0]
    x0_u, m_u = item["x0_u"][None], item["m_u"][None]
    trained = complete(load_generator(tmp_path / "overfit"), x0_u, m_u, 8, torch.Generator().manual_seed(0))["x0"]
    untrained = complete((build_net(cfg).eval(), cfg), x0_u, m_u, 8, torch.Generator().manual_seed(0))["x0"]
    error = float((trained[0] - item["x0"]).abs().mean())
    error_untrained = float((untrained[0] - item["x0"]).abs().mean())
    assert error < 0.5 * error_untrained, (error, error_untrained)


TINY_MOST = TINY.with_name("tiny_most.yaml")


def tiny_most_config(world: tuple[Path, Path], out: Path, stage: str, *extra: str) -> DiffusionTrainConfig:
    overrides = [f"data_root={world[0]}", f"probs_root={world[1]}", f"out={out}", f"diffusion.stage={stage}", *extra]
    return load_config(DiffusionTrainConfig, TINY_MOST, overrides)


def test_frames_items_are_windows_of_one_sequence(tiny_world, tmp_path):
    from u4d_aug.train import RangeImages

    images = RangeImages(tiny_most_config(tiny_world, tmp_path / "x", "stage2"))
    assert len(images) == 2  # 3 scans -> windows (0, 1), (1, 2)
    assert images.window(1) == ("00", ["000001", "000002"])
    item = images[1]
    assert item["x0"].shape == (2, 2, 16, 64) and item["x0_u"].shape == (2, 2, 16, 64)
    assert item["m_u"].shape == (2, 1, 16, 64)
    single = RangeImages(tiny_config(tiny_world, tmp_path / "y", "stage2"))
    assert torch.equal(item["x0"][0], single[1]["x0"]) and torch.equal(item["m_u"][1], single[2]["m_u"])
    strided = RangeImages(tiny_most_config(tiny_world, tmp_path / "z", "baseline", "frame_stride=2"))
    assert len(strided) == 1 and strided.window(0) == ("00", ["000000", "000002"])
    with pytest.raises(InputError, match="window"):
        RangeImages(tiny_most_config(tiny_world, tmp_path / "w", "baseline", "frames=4"))
    with pytest.raises(InputError, match="frames"):
        tiny_most_config(tiny_world, tmp_path / "v", "baseline", "frames=0")


def test_frames_training_logs_gates_and_resumes_exactly(tiny_world, tmp_path):
    full = tiny_most_config(tiny_world, tmp_path / "full", "stage2", "sample_every=4")
    record = train(full, progress=False)
    assert record["step"] == 4 and np.isfinite(record["loss"]) and record["most_cv"] >= 0
    assert record["most_blocks"] == ["enc0", "enc1", "mid", "dec1", "dec0"]
    alpha_s, alpha_t = np.array(record["most_alpha_s"]), np.array(record["most_alpha_t"])
    assert alpha_s.shape == (5,) and np.all((alpha_s > 0) & (alpha_s < 1))
    np.testing.assert_allclose(alpha_s + alpha_t, 1.0, atol=2e-4)  # rounded to 4 decimals
    assert (tmp_path / "full" / "samples" / "step_0000004.png").is_file()
    assert (tmp_path / "full" / "samples" / "gates_0000004.png").is_file()
    ckpt = torch.load(tmp_path / "full" / "checkpoints" / "step_0000004.pt", weights_only=False)
    assert ckpt["config"]["frames"] == 2 and ckpt["config"]["net"]["most"] is True
    assert any(name.startswith("most_") for name in ckpt["model"])

    train(tiny_most_config(tiny_world, tmp_path / "part", "stage2", "steps=2"), progress=False)
    resumed = train(tiny_most_config(tiny_world, tmp_path / "part", "stage2"), resume="last", progress=False)
    assert resumed["step"] == 4 and resumed["loss"] == record["loss"]
    assert resumed["most_alpha_t"] == record["most_alpha_t"]
    b = torch.load(tmp_path / "part" / "checkpoints" / "step_0000004.pt", weights_only=False)
    for name, value in ckpt["model"].items():
        torch.testing.assert_close(b["model"][name], value)


def test_frames_without_most_train_frames_independently(tiny_world, tmp_path):
    cfg = tiny_most_config(tiny_world, tmp_path / "plain", "baseline", "net.most=false", "steps=2")
    record = train(cfg, progress=False)
    assert record["step"] == 2 and "most_cv" not in record and "most_alpha_s" not in record
