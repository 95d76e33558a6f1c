"""`u4d train-autoencoder`: a few steps on tiny synthetic scans with probabilities; its files, the weights it leaves,
exact resume through the CLI, the x0_u / x0 mix and the crops of a step, the run lock."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import REPO
from tests.tiny_worlds import write_tiny_world
from u4d_aug.autoencoder_stage import WEIGHTS_KIND, AutoencoderTrainConfig, build_autoencoder, load_autoencoder
from u4d_aug.batches import batch_indices
from u4d_aug.cli import main
from u4d_aug.config import config_to_dict, load_config
from u4d_aug.errors import InputError
from u4d_aug.io import read_jsonl
from u4d_aug.runlock import LOCK_NAME
from u4d_aug.train_autoencoder import (
    CHECKPOINT_KIND,
    column_weight,
    image_source,
    statistic_images,
    train,
    training_images,
)

PRESET = REPO / "configs" / "u4d" / "autoencoder_hdl64.yaml"
# the shipped preset shrunk to configs/u4d/tiny.yaml's 16x64 linear rows and a factor-2 net of 8 channels
TINY = (
    "sequences=null", "height=16", "width=64", "row_mode=linear", "crop_width=32", "crop_margin=4",
    "ae.base_channels=8", "ae.channel_multipliers=[1,2]", "ae.z_channels=4", "ae.gn_groups=4",
    "steps=4", "batch_size=2", "log_every=2", "checkpoint_every=2", "stats_scans=3", "optim.warmup_steps=1",
    "device=cpu",
)  # fmt: skip
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """3 random-ray scans and their class probabilities (tests/tiny_worlds.py), read-only for every test here."""
    folder = tmp_path_factory.mktemp("ae_world")
    write_tiny_world(folder / "world", folder / "probs")
    return folder / "world", folder / "probs"


def overrides(world: tuple[Path, Path], *extra: str) -> list[str]:
    return [f"data_root={world[0]}", f"probs_root={world[1]}", *TINY, *extra]


def tiny_config(world: tuple[Path, Path], out: Path, *extra: str) -> AutoencoderTrainConfig:
    """The tiny preset on `world`, writing to `out`, + overrides."""
    return load_config(AutoencoderTrainConfig, PRESET, overrides(world, f"out={out}", *extra))


@pytest.fixture(scope="module")
def run(world, tmp_path_factory) -> tuple[AutoencoderTrainConfig, dict]:
    """One uninterrupted 4-step run (half of each batch x0_u) and its last logged record."""
    cfg = tiny_config(world, tmp_path_factory.mktemp("ae_runs") / "full")
    return cfg, train(cfg, progress=False)


def test_a_run_writes_checkpoints_log_weights_and_a_reconstruction(run):
    cfg, record = run
    out = Path(cfg.out)
    assert record["step"] == 4 and np.isfinite(record["loss"]) and record["lr"] == cfg.optim.lr
    assert {"loss", "l1", "l1_depth", "mask_bce", "kl", "grad_norm"} <= set(record)
    assert [r["step"] for r in read_jsonl(out / "log.jsonl")] == [2, 4]
    assert [c.name for c in sorted((out / "checkpoints").glob("step_*.pt"))] == ["step_0000002.pt", "step_0000004.pt"]
    ckpt = torch.load(out / "checkpoints" / "step_0000004.pt", weights_only=True)
    assert ckpt["kind"] == CHECKPOINT_KIND and ckpt["step"] == 4 and ckpt["optimizer"] is not None
    assert ckpt["config"] == config_to_dict(cfg)
    initial = build_autoencoder(cfg.ae, cfg.seed).state_dict()
    assert not torch.equal(ckpt["model"]["encoder.0.weight"], initial["encoder.0.weight"])  # it trained
    weights = torch.load(out / "autoencoder.pt", weights_only=True)
    assert weights["kind"] == WEIGHTS_KIND and weights["config"] == config_to_dict(cfg)
    assert (out / "config.yaml").is_file() and not (out / LOCK_NAME).exists()
    assert (out / "reconstruction.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_load_autoencoder_gives_the_trained_net_normalised_on_training_scans(run):
    """autoencoder.pt = the last step's weights + latent statistics of the `statistic_images`, whose latents it
    then maps to zero mean and unit std per channel; a run folder stands for its autoencoder.pt."""
    cfg, _ = run
    out = Path(cfg.out)
    net, loaded_cfg = load_autoencoder(out)
    from_file, _ = load_autoencoder(out / "autoencoder.pt")
    assert loaded_cfg == cfg and not net.training
    trained = build_autoencoder(cfg.ae, 0)
    trained.load_state_dict(torch.load(out / "checkpoints" / "step_0000004.pt", weights_only=True)["model"])
    trained.eval()
    images = statistic_images(image_source(cfg), cfg)
    assert images.shape == (3, 2, 16, 64)
    with torch.no_grad():
        trained.set_latent_statistics(trained.encode(images)[0])
        for name, value in trained.state_dict().items():
            torch.testing.assert_close(net.state_dict()[name], value, msg=name)
            assert torch.equal(from_file.state_dict()[name], net.state_dict()[name]), name
        z = net.to_latent(images)
        torch.testing.assert_close(z.mean(dim=(0, 2, 3)), torch.zeros(4), atol=1e-4, rtol=0)
        torch.testing.assert_close(z.std(dim=(0, 2, 3)), torch.ones(4), atol=1e-4, rtol=0)
        torch.testing.assert_close(net.from_latent(z), trained.from_latent(trained.to_latent(images)))


def test_resume_through_the_cli_ends_with_the_weights_of_an_uninterrupted_run(run, world, tmp_path, capsys):
    cfg, record = run
    part = tmp_path / "part"
    command = ["train-autoencoder", str(PRESET), *overrides(world), "--out", str(part), "--no-progress"]
    assert main([*command, "steps=2"]) == 0
    assert [c.name for c in (part / "checkpoints").glob("step_*.pt")] == ["step_0000002.pt"]
    assert main(command) == 2  # a folder that holds a run is not started again without --resume
    assert "--resume" in capsys.readouterr().err
    with pytest.warns(UserWarning, match="steps: 2 -> 4"):
        assert main([*command, "--resume"]) == 0
    assert [r["step"] for r in read_jsonl(part / "log.jsonl")] == [2, 4]
    assert read_jsonl(part / "log.jsonl")[-1]["loss"] == record["loss"]
    full, resumed = (torch.load(Path(run) / "autoencoder.pt", weights_only=True) for run in (cfg.out, part))
    assert full["model"].keys() == resumed["model"].keys()
    for name, value in full["model"].items():
        assert torch.equal(resumed["model"][name], value), name
    a, b = (torch.load(Path(run) / "checkpoints" / "step_0000004.pt", weights_only=True) for run in (cfg.out, part))
    for index, state in a["optimizer"]["state"].items():
        for key, value in state.items():
            assert torch.equal(b["optimizer"]["state"][index][key], value), (index, key)


def test_x0_u_images_need_the_probabilities(world, tmp_path):
    out = tmp_path / "no_probs"
    with pytest.raises(InputError, match="probs_root"):
        train(tiny_config(world, out, "probs_root=''"), progress=False)
    assert not (out / LOCK_NAME).exists() and not (out / "checkpoints").exists()
    full_scans_only = image_source(tiny_config(world, out, "probs_root=''", "uncertain_share=0"))
    assert set(full_scans_only[0]) == {"x0"}  # no probabilities needed when every image is a full scan


@pytest.mark.parametrize(("share", "uncertain"), [(0.0, 0), (0.25, 1), (0.5, 2), (0.75, 3)])
def test_a_step_takes_x0_u_for_the_first_share_of_its_batch(world, tmp_path, share, uncertain):
    cfg = tiny_config(world, tmp_path, f"uncertain_share={share}", "batch_size=4", "crop_width=0", "crop_margin=0")
    images = image_source(cfg)
    x, _ = training_images(images, cfg, 5, 0, CPU)
    indices = batch_indices(5, 0, len(images), 4, cfg.seed)
    assert x.shape == (4, 2, 16, 64)
    for position, index in enumerate(indices):
        key = "x0_u" if position < uncertain else "x0"
        assert torch.equal(x[position], images[index][key]), (position, key)
        if key == "x0_u":  # the uncertain region alone: a strict part of the scan's returns
            assert not torch.equal(x[position], images[index]["x0"])


def test_a_step_crops_every_image_at_a_multiple_of_the_latent_factor(world, tmp_path):
    cfg = tiny_config(world, tmp_path, "batch_size=4", "crop_width=32", "crop_margin=4")
    full_cfg = tiny_config(world, tmp_path, "batch_size=4", "crop_width=0", "crop_margin=0")
    images = image_source(cfg)
    offsets = []
    for step in range(3):
        x, generator = training_images(images, cfg, step, 0, CPU)
        again, generator_again = training_images(images, cfg, step, 0, CPU)
        assert x.shape == (4, 2, 16, 32) and torch.equal(x, again)  # the step decides scans, crops and noise
        assert torch.equal(torch.randn(3, generator=generator), torch.randn(3, generator=generator_again))
        full, _ = training_images(images, full_cfg, step, 0, CPU)
        for crop, scan in zip(x, full):
            found = [o for o in range(64) if torch.equal(crop, scan[..., (o + torch.arange(32)) % 64])]
            assert found and all(o % cfg.ae.factor == 0 for o in found), found
            offsets.append(found[0])
    assert len(set(offsets)) > 1
    weight = column_weight(cfg, CPU)
    assert weight.tolist() == [0.0] * 4 + [1.0] * 24 + [0.0] * 4


def test_a_run_on_an_out_that_another_run_holds_is_refused(world, tmp_path):
    """OUT/.lock of a live run (one on another machine cannot be checked, so it counts as live): refused at once,
    with one line naming the holder, and the holder's lock and folder left as they were."""
    out = tmp_path / "locked"
    out.mkdir()
    holder = {"pid": 1, "host": "another-machine", "start": None}
    (out / LOCK_NAME).write_text(json.dumps(holder))
    with pytest.raises(InputError, match="in use by another run \\(pid 1 on host another-machine"):
        train(tiny_config(world, out), progress=False)
    assert json.loads((out / LOCK_NAME).read_text()) == holder
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]


def test_other_files_are_refused_as_autoencoder_weights_and_as_checkpoints(run, world, tmp_path):
    cfg, _ = run
    out = Path(cfg.out)
    with pytest.raises(InputError, match="not the autoencoder weights of `u4d train-autoencoder`"):
        load_autoencoder(out / "checkpoints" / "step_0000004.pt")  # a training checkpoint is not the weights file
    with pytest.raises(InputError, match="not found"):
        load_autoencoder(out / "checkpoints")  # a folder without autoencoder.pt
    with pytest.raises(InputError, match="not a u4d train-autoencoder checkpoint"):
        train(tiny_config(world, tmp_path / "new"), resume=out / "autoencoder.pt", progress=False)


def test_setting_one_optim_key_keeps_the_default_learning_rate():
    default = AutoencoderTrainConfig().optim.lr
    assert load_config(AutoencoderTrainConfig, None, ["optim.warmup_steps=1"]).optim.lr == default


def test_a_run_stopped_by_its_time_budget_leaves_its_weights(world, tmp_path):
    cfg = tiny_config(world, tmp_path / "budget", "max_minutes=1e-9", "steps=100")
    record = train(cfg, progress=False)
    assert record["step"] == 1  # the budget was used after the first step
    loaded, _ = load_autoencoder(tmp_path / "budget")
    assert (tmp_path / "budget" / "reconstruction.png").is_file() and not loaded.training


def test_two_process_training_equals_two_ranks_in_one_process(world, tmp_path):
    from tests.tiny_nets import torchrun
    from u4d_aug.train import learning_rate

    out = tmp_path / "ddp"
    torchrun("-m", "u4d_aug.cli", "train-autoencoder", str(PRESET), *overrides(world, "steps=2", "log_every=1"),
             "--out", str(out), "--no-progress")  # fmt: skip
    assert [r["step"] for r in read_jsonl(out / "log.jsonl")] == [1, 2]  # rank 0 logs once per logging step
    ckpt = torch.load(out / "checkpoints" / "step_0000002.pt", weights_only=True)
    cfg = tiny_config(world, out, "steps=2")
    images = image_source(cfg)
    net = build_autoencoder(cfg.ae, cfg.seed)
    optimizer = torch.optim.AdamW(net.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas,
                                  weight_decay=cfg.optim.weight_decay)  # fmt: skip
    for step in range(2):
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(step, cfg.optim, cfg.steps)
        optimizer.zero_grad(set_to_none=True)
        for rank in range(2):  # DDP's gradient is the mean of the ranks'
            x, generator = training_images(images, cfg, step, rank, CPU)
            loss = net(x, generator, cfg.kl_weight, cfg.mask_weight, column_weight(cfg, CPU), cfg.value_weights)
            (loss["loss"] / 2).backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.optim.grad_clip)
        optimizer.step()
    for name, value in net.state_dict().items():
        torch.testing.assert_close(ckpt["model"][name], value, rtol=1e-5, atol=1e-6, msg=name)
    assert (out / "autoencoder.pt").is_file()
