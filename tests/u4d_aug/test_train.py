"""`u4d train-diffusion`: a few steps of each stage on tiny synthetic scans, checkpoints, log, resume."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import REPO, TINY, diffusion_config, plain_settings
from tests.tiny_worlds import write_tiny_world
from u4d_aug.batches import RangeImages, crop_batch
from u4d_aug.config import load_config
from u4d_aug.data.formats import write_kitti_scan
from u4d_aug.diffusion import GaussianDiffusion
from u4d_aug.errors import InputError
from u4d_aug.io import read_jsonl
from u4d_aug.stage import DiffusionTrainConfig
from u4d_aug.train import add_train_diffusion_arguments, run_train_diffusion, train
from u4d_aug.validate import NonFiniteLossError


@pytest.fixture
def tiny_world(tmp_path: Path) -> tuple[Path, Path]:
    root, probs_root = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(root, probs_root)
    return root, probs_root


@pytest.mark.parametrize("stage", ["stage1", "stage2", "baseline"])
def test_each_stage_trains_and_writes_checkpoint_and_log(tiny_world, tmp_path, stage):
    out = tmp_path / f"run_{stage}"
    cfg = diffusion_config(tiny_world, out, stage)
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
    full = diffusion_config(tiny_world, tmp_path / "full", "stage2")
    train(full, progress=False)
    part = diffusion_config(tiny_world, tmp_path / "part", "stage2", "steps=2")
    train(part, progress=False)
    with pytest.raises(InputError, match="--resume"):
        train(diffusion_config(tiny_world, tmp_path / "part", "stage2"), progress=False)
    # a new process resumes from the checkpoint of step 2 (nothing of the first run's memory reaches it)
    subprocess.run(
        [sys.executable, "-m", "u4d_aug.cli", "train-diffusion", str(TINY), f"data_root={tiny_world[0]}",
         f"probs_root={tiny_world[1]}", "stage=stage2", "--out", str(tmp_path / "part"), "--resume", "--no-progress"],
        check=True, cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, timeout=300,
    )  # fmt: skip
    assert [r["step"] for r in read_jsonl(tmp_path / "part" / "log.jsonl")] == [2, 4]
    a = torch.load(tmp_path / "full" / "checkpoints" / "step_0000004.pt", weights_only=False)
    b = torch.load(tmp_path / "part" / "checkpoints" / "step_0000004.pt", weights_only=False)
    assert_same_training_state(a, b)
    assert (
        read_jsonl(tmp_path / "part" / "log.jsonl")[-1]["loss"]
        == read_jsonl(tmp_path / "full" / "log.jsonl")[-1]["loss"]
    )


def assert_same_training_state(a: dict, b: dict) -> None:
    """Bit for bit: the scans and noise of step s depend only on (seed, step, rank), so a resumed run ends with the
    model, EMA and optimizer state of an uninterrupted one (same device, same world size)."""
    assert a["step"] == b["step"]
    assert a["model"].keys() == b["model"].keys() and a["ema"]["params"].keys() == b["ema"]["params"].keys()
    for name, value in a["model"].items():
        assert torch.equal(b["model"][name], value), name
    for name, value in a["ema"]["params"].items():
        assert torch.equal(b["ema"]["params"][name], value), name
    assert a["ema"]["num_updates"] == b["ema"]["num_updates"]
    for index, state in a["optimizer"]["state"].items():
        for key, value in state.items():
            assert torch.equal(b["optimizer"]["state"][index][key], value), (index, key)


def test_a_run_killed_before_its_first_checkpoint_starts_again_from_step_0(tiny_world, tmp_path, caplog):
    """Issue 44: a process killed (SIGKILL) before its first checkpoint leaves config, log, lock and perhaps temp
    files; the next run, with or without --resume, takes over the stale lock and trains from step 0."""
    out = tmp_path / "killed"
    code = (
        "import sys; from u4d_aug.cli import main; "
        f"sys.exit(main(['train-diffusion', {str(TINY)!r}, 'stage=baseline', 'data_root={tiny_world[0]}', "
        f"'steps=100000', 'log_every=1', 'checkpoint_every=100000', '--out', {str(out)!r}, '--no-progress']))"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (out / "log.jsonl").is_file() or not (out / "log.jsonl").read_text().strip():
            assert process.poll() is None, process.stderr.read()
            assert time.monotonic() < deadline, "the run wrote no log line in 120 s"
            time.sleep(0.2)
        assert "in use by another run" in "".join(_refusal(tiny_world, out))  # a second run while it lives
    finally:
        process.kill()
        process.wait()
    assert (out / ".lock").is_file() and not (out / "checkpoints").exists()
    (out / "checkpoints").mkdir()
    (out / "checkpoints" / ".step_0000002.pt.k1ll3d.tmp").write_bytes(b"half a checkpoint")
    with caplog.at_level("INFO", logger="u4d_aug"):
        record = train(diffusion_config(tiny_world, out, "baseline"), progress=False)
    assert "took over the lock" in caplog.text and "starting it again from step 0" in caplog.text
    assert record["step"] == 4 and [r["step"] for r in read_jsonl(out / "log.jsonl")] == [2, 4]
    assert not list(out.rglob("*.tmp")) and not (out / ".lock").exists()

    fresh = tmp_path / "fresh"
    train(diffusion_config(tiny_world, fresh, "baseline"), progress=False)
    unfinished = tmp_path / "unfinished"  # --resume before the first checkpoint: step 0 as well
    unfinished.mkdir()
    (unfinished / "config.yaml").write_text("steps: 4\n")
    (unfinished / "log.jsonl").write_text('{"step": 1, "loss": 9.0}\n')
    assert train(diffusion_config(tiny_world, unfinished, "baseline"), resume="last", progress=False)["step"] == 4
    assert [r["step"] for r in read_jsonl(unfinished / "log.jsonl")] == [2, 4]
    a = torch.load(fresh / "checkpoints" / "step_0000004.pt", weights_only=True)
    for run in (out, unfinished):
        b = torch.load(run / "checkpoints" / "step_0000004.pt", weights_only=True)
        for name, value in a["model"].items():
            torch.testing.assert_close(b["model"][name], value)


def test_resuming_with_another_net_width_names_the_changed_key(tiny_world, tmp_path):
    out = tmp_path / "run"
    train(diffusion_config(tiny_world, out, "baseline", "steps=2", "checkpoint_every=2"), progress=False)
    wider = diffusion_config(tiny_world, out, "baseline", "steps=4", "net.base_channels=16")
    with pytest.warns(UserWarning), pytest.raises(InputError) as info:
        train(wider, resume="last", progress=False)
    message = str(info.value)
    assert "step_0000002.pt (model): its weights do not fit the net" in message and "\n" not in message
    assert "net.base_channels: 8 -> 16" in message  # the key that changed the architecture


def _refusal(tiny_world, out: Path) -> list[str]:
    """The error a second `train` on `out` raises, as a list of one message (empty when it was not refused)."""
    try:
        train(diffusion_config(tiny_world, out, "baseline"), progress=False)
    except InputError as error:
        return [str(error)]
    return []


def test_a_non_finite_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tiny_world, tmp_path, monkeypatch):
    out = tmp_path / "nan"
    train(diffusion_config(tiny_world, out, "baseline", "steps=2"), progress=False)
    forward = GaussianDiffusion.forward

    def nan_at_step_3(self, x0, *args, **kwargs):
        losses = forward(self, x0, *args, **kwargs)
        return {**losses, "loss": losses["loss"] * float("nan")}

    monkeypatch.setattr(GaussianDiffusion, "forward", nan_at_step_3)
    with pytest.raises(NonFiniteLossError, match="training step 3: the loss is nan"):
        train(diffusion_config(tiny_world, out, "baseline", "checkpoint_every=1"), resume="last", progress=False)
    assert [c.name for c in sorted((out / "checkpoints").glob("step_*.pt"))] == ["step_0000002.pt"]
    state = torch.load(out / "checkpoints" / "step_0000002.pt", weights_only=True)
    assert all(torch.isfinite(value).all() for value in state["model"].values())
    assert not (out / ".lock").exists()  # released on the error


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
    record = train(diffusion_config(tiny_world, out, "baseline", "steps=50", "max_minutes=1e-9"), progress=False)
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
        train(diffusion_config(tiny_world, tmp_path / "x", "stage1", "probs_root=''"), progress=False)


@pytest.mark.slow
def test_stage2_overfits_one_scan(tmp_path):
    """Stage 2 trained on one scan completes that scan's x0_u far closer to it than the untrained net (~35 s)."""
    from u4d_aug.pipeline import complete, load_generator
    from u4d_aug.stage import build_net

    world = (tmp_path / "world", tmp_path / "probs")
    write_tiny_world(*world, num_scans=1)
    cfg = diffusion_config(
        world, tmp_path / "overfit", "stage2",
        "steps=200", "checkpoint_every=1000", "log_every=50", "optim.lr=0.003", "ema_decay=0.0", "batch_size=4",
        "diffusion.min_snr_gamma=null",
    )  # fmt: skip
    train(cfg, progress=False)
    item = RangeImages(cfg)[0]
    x0_u, m_u = item["x0_u"][None], item["m_u"][None]
    ddim = plain_settings(8)
    trained = complete(load_generator(tmp_path / "overfit"), x0_u, m_u, torch.Generator().manual_seed(0), ddim)["x0"]
    untrained = complete((build_net(cfg).eval(), cfg), x0_u, m_u, torch.Generator().manual_seed(0), ddim)["x0"]
    error = float((trained[0] - item["x0"]).abs().mean())
    error_untrained = float((untrained[0] - item["x0"]).abs().mean())
    assert error < 0.5 * error_untrained, (error, error_untrained)


TINY_MOST = TINY.with_name("tiny_most.yaml")


def tiny_most_config(world: tuple[Path, Path], out: Path, stage: str, *extra: str) -> DiffusionTrainConfig:
    overrides = [f"data_root={world[0]}", f"probs_root={world[1]}", f"out={out}", f"diffusion.stage={stage}", *extra]
    return load_config(DiffusionTrainConfig, TINY_MOST, overrides)


def test_frames_items_are_windows_of_one_sequence(tiny_world, tmp_path):
    images = RangeImages(tiny_most_config(tiny_world, tmp_path / "x", "stage2"))
    assert len(images) == 2  # 3 scans -> windows (0, 1), (1, 2)
    assert images.window(1) == ("00", ["000001", "000002"])
    item = images[1]
    assert item["x0"].shape == (2, 2, 16, 64) and item["x0_u"].shape == (2, 2, 16, 64)
    assert item["m_u"].shape == (2, 1, 16, 64)
    single = RangeImages(diffusion_config(tiny_world, tmp_path / "y", "stage2"))
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
    assert_same_training_state(
        ckpt, torch.load(tmp_path / "part" / "checkpoints" / "step_0000004.pt", weights_only=False)
    )


def test_frames_without_most_train_frames_independently(tiny_world, tmp_path):
    cfg = tiny_most_config(tiny_world, tmp_path / "plain", "baseline", "net.most=false", "steps=2")
    record = train(cfg, progress=False)
    assert record["step"] == 2 and "most_cv" not in record and "most_alpha_s" not in record


def test_crop_training_gives_the_full_width_loss_and_gradient_on_a_ring_symmetric_scan(generator):
    """On a panorama (x_t and ε) that repeats every crop width, the ε-loss of a crop and its gradient equal the
    full-width ones: the crop is padded as a ring of its own and the net has no azimuth features here."""
    from u4d_aug.nn.unet import RangeUNet, UNetConfig

    cfg = UNetConfig(base_channels=8, channel_multipliers=(1, 2), num_res_blocks=1, attention=True,
                     attention_heads=2, fourier_features=False, gn_groups=4)  # fmt: skip
    net = RangeUNet(cfg)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=generator) * 0.2)
    x_t = torch.randn(2, 2, 8, 16, generator=generator).repeat(1, 1, 1, 4)  # (B, 2, H, 64), period 16
    eps = torch.randn(2, 2, 8, 16, generator=generator).repeat(1, 1, 1, 4)
    log_snr = torch.tensor([0.0, 2.0])
    offsets = torch.tensor([2, 40])
    losses, grads = [], []
    for images, kwargs in (  # x_t and ε carried under image keys, so crop_batch crops them as it crops x0 and x0_u
        ({"x0": x_t, "x0_u": eps}, {}),
        (crop_batch({"x0": x_t, "x0_u": eps}, offsets, 16), {"crop_offsets": offsets}),
    ):
        net.zero_grad()
        loss = (net(images["x0"], log_snr, **kwargs)[0] - images["x0_u"]).square().mean()
        loss.backward()
        losses.append(loss.detach())
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
    torch.testing.assert_close(losses[1], losses[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-5 * grads[0].abs().max().item())


def write_ring_world(root: Path, num_points: int = 40_000) -> None:
    """One scan whose depth varies smoothly with azimuth and is continuous across the ±180° seam."""
    rng = np.random.default_rng(1)
    elevation = np.deg2rad(rng.uniform(-24.0, 2.0, num_points))
    azimuth = rng.uniform(-np.pi, np.pi, num_points)
    depth = 20.0 + 8.0 * np.sin(azimuth) + 4.0 * np.cos(2 * azimuth) + 10.0 * (elevation - elevation.min())
    xyz = np.stack([depth * np.cos(elevation) * np.cos(azimuth), depth * np.cos(elevation) * np.sin(azimuth),
                    depth * np.sin(elevation)], axis=1)  # fmt: skip
    points = np.concatenate([xyz, 0.5 + 0.3 * np.cos(azimuth)[:, None]], axis=1).astype(np.float32)
    write_kitti_scan(root / "sequences" / "00" / "velodyne" / "000000.bin", points)


@pytest.mark.slow
def test_full_width_sample_of_a_crop_trained_net_closes_the_ring(tmp_path):
    """Trained on 90-degree crops only, the net samples the whole 360 degrees: the right shape, and no seam where
    the panorama's first and last columns meet (their difference is like any two neighbouring columns') (~35 s)."""
    from u4d_aug.pipeline import generate_baseline, load_generator

    write_ring_world(tmp_path / "ring")
    cfg = diffusion_config(
        (tmp_path / "ring", tmp_path / "none"), tmp_path / "crop", "baseline",
        "crop_width=16", "steps=600", "batch_size=4", "checkpoint_every=1000", "log_every=100", "optim.lr=0.003",
        "ema_decay=0.0", "diffusion.min_snr_gamma=null",
    )  # fmt: skip
    train(cfg, progress=False)
    ddpm = plain_settings(8, "ddpm")
    x0 = generate_baseline(load_generator(tmp_path / "crop"), 2, torch.Generator().manual_seed(0), ddpm)["x0"]
    assert x0.shape == (2, 2, 16, 64) and torch.isfinite(x0).all()
    steps = (x0 - torch.roll(x0, 1, -1)).abs().mean(dim=(1, 2))  # (2, W): column j against column j - 1
    seam, inner = steps[:, 0], steps[:, 1:]
    assert (seam <= inner.quantile(0.9, dim=1)).all(), (seam, inner.median(dim=1).values)
    target = RangeImages(cfg)[0]["x0"]
    assert (x0 - target).abs().mean() < 0.2  # it learned the ring scan (a random image is ~0.7 away)


def test_sequence_items_carry_the_ego_motion_that_reaches_the_net(tmp_path):
    """With net.pose_dim, an L-frame item holds the frames' motion (x, y, z, yaw) from poses.txt; training runs."""
    from u4d_aug.data.formats import write_calib, write_poses
    from u4d_aug.trajectory import poses_from_motion, straight_motion

    world = (tmp_path / "world", tmp_path / "probs")
    write_tiny_world(*world, num_scans=4)
    truth = straight_motion(4, 1.5, yaw_rate=0.1)  # the vehicle drives 1.5 m per frame, turning left
    folder = world[0] / "sequences" / "00"
    write_calib(folder / "calib.txt", {"P0": np.eye(4)[:3], "Tr": np.eye(4)[:3]})
    write_poses(folder / "poses.txt", poses_from_motion(truth, poses_from_motion(np.array([[3.0, 4.0, 0, 1.0]]))[0]))
    cfg = tiny_most_config(world, tmp_path / "run", "stage2", "net.pose_dim=4", "crop_width=32", "steps=2")
    images = RangeImages(cfg)
    item = images[1]  # frames 1, 2: motion in frame 1's sensor frame, which already heads 0.1 rad to the left
    assert item["x0"].shape == (2, 2, 16, 64) and item["motion"].shape == (2, 4)
    np.testing.assert_allclose(item["motion"].numpy(), [[0, 0, 0, 0], [1.5, 0, 0, 0.1]], atol=1e-5)
    cropped = crop_batch({k: v[None] for k, v in item.items()}, torch.tensor([8]), 32)
    assert cropped["x0"].shape[-1] == 32 and torch.equal(cropped["motion"][0], item["motion"])
    record = train(cfg, progress=False)
    assert record["step"] == 2 and np.isfinite(record["loss"])
