"""u4d_aug.batches: azimuth crops wrap around the ring; a step's batch and noise depend on (seed, step, rank) only;
stage 2's propagated condition (in a u4d batch, its stage-2 samples' only)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.tiny_nets import TINY_MOST, diffusion_config
from tests.tiny_worlds import write_posed_world, write_tiny_world
from u4d_aug.batches import RangeImages, crop_batch, row_mean, row_mean_key, training_batch
from u4d_aug.config import load_config
from u4d_aug.data.sensors import get_sensor
from u4d_aug.errors import InputError
from u4d_aug.propagate import warp_frame0
from u4d_aug.stage import DiffusionTrainConfig


def test_crop_batch_wraps_around_the_ring():
    image = torch.arange(8.0).expand(2, 3, 1, 4, 8)  # (B, L, C, H, W), value = column
    cropped = crop_batch({"x0": image}, torch.tensor([6, 2]), 4)["x0"]
    assert cropped.shape == (2, 3, 1, 4, 4)
    assert cropped[0, 0, 0, 0].tolist() == [6, 7, 0, 1] and cropped[1, 2, 0, 3].tolist() == [2, 3, 4, 5]


def test_a_steps_batch_and_noise_depend_on_seed_step_and_rank_only(tmp_path):
    world = (tmp_path / "world", tmp_path / "probs")
    write_tiny_world(*world, num_scans=3)
    cfg = diffusion_config(world, tmp_path / "run", "stage2", "crop_width=32", "batch_size=4")
    images = RangeImages(cfg)
    draws = {}
    for key in [(5, 0), (5, 0), (5, 1), (6, 0)]:  # (step, rank)
        batch, offsets, generator = training_batch(images, cfg, *key, torch.device("cpu"))
        assert batch["x0"].shape == (4, 2, 16, 32) and batch["m_u"].shape == (4, 1, 16, 32)
        draws.setdefault(key, []).append((batch["x0"], offsets, torch.randn(3, generator=generator)))
    (a_x0, a_offsets, a_noise), (b_x0, b_offsets, b_noise) = draws[(5, 0)]
    assert torch.equal(a_x0, b_x0) and torch.equal(a_offsets, b_offsets) and torch.equal(a_noise, b_noise)
    for other in ((5, 1), (6, 0)):  # another rank or step draws other crops and noise
        x0, offsets, noise = draws[other][0]
        assert not torch.equal(noise, a_noise) and not (torch.equal(offsets, a_offsets) and torch.equal(x0, a_x0))


def test_propagated_share_conditions_windows_on_frame_0_moved_along_their_poses(tmp_path):
    world = (tmp_path / "world", tmp_path / "probs")
    poses = write_posed_world(*world, num_scans=3)
    config = load_config(DiffusionTrainConfig, TINY_MOST, [f"data_root={world[0]}", f"probs_root={world[1]}"])
    stage2 = dataclasses.replace(config, diffusion=dataclasses.replace(config.diffusion, stage="stage2"))
    sensor = get_sensor(stage2.sensor)

    always = RangeImages(dataclasses.replace(stage2, propagated_share=1.0))
    item = always.__getitem__(0, torch.Generator().manual_seed(0))  # window of frames 0, 1
    x0_u, m_u = warp_frame0(item["x0"][0], poses[:2], sensor, stage2.row_mode)
    assert torch.equal(item["x0_u"], x0_u) and torch.equal(item["m_u"], m_u)
    assert item["m_u"][0].all() and 0.3 < float(item["m_u"][1].mean()) < 1.0  # frame 1: the part frame 0 reaches
    plain = RangeImages(stage2)[0]  # share 0: each frame's P_u, as the paper trains
    assert not torch.equal(plain["m_u"], item["m_u"]) and float(plain["m_u"].mean()) < 0.5
    assert torch.equal(always[0]["m_u"], plain["m_u"])  # no generator (row means, figures): P_u

    half = RangeImages(dataclasses.replace(stage2, propagated_share=0.5))
    picks = [
        bool(half.__getitem__(0, torch.Generator().manual_seed(seed))["m_u"][0].all()) for seed in range(40)
    ]  # fmt: skip
    assert 10 < sum(picks) < 30  # about half the draws, decided by the generator
    again = [bool(half.__getitem__(0, torch.Generator().manual_seed(s))["m_u"][0].all()) for s in range(40)]
    assert again == picks

    # the mean start's x0 mean does not depend on the condition (it is read as a baseline's, without one)
    assert torch.equal(row_mean(dataclasses.replace(stage2, propagated_share=0.5)), row_mean(stage2))

    for bad, why in ((["propagated_share=1.5"], "in \\[0, 1\\]"), (["propagated_share=0.5", "frames=1"], "frames")):
        with pytest.raises(InputError, match=why):
            load_config(DiffusionTrainConfig, TINY_MOST, ["diffusion.stage=stage2", *bad])
    with pytest.raises(InputError, match="stage baseline"):
        load_config(DiffusionTrainConfig, TINY_MOST, ["propagated_share=0.5"])


def test_a_u4d_batch_propagates_only_the_condition_of_its_stage_2_windows(tmp_path):
    world = (tmp_path / "world", tmp_path / "probs")
    write_posed_world(*world, num_scans=3)
    overrides = [f"data_root={world[0]}", f"probs_root={world[1]}", "diffusion.stage=u4d", "batch_size=4"]
    cfg = load_config(DiffusionTrainConfig, TINY_MOST, [*overrides, "propagated_share=1.0"])
    batch, _, _ = training_batch(RangeImages(cfg), cfg, 0, 0, torch.device("cpu"))
    frame0_known = [bool(m_u[0].all()) for m_u in batch["m_u"]]  # (B, L, 1, H, W): a propagated window knows frame 0
    assert frame0_known == [False, False, True, True]  # stage 1 learns P_u itself; stage 2 reads the propagated frame
    plain = load_config(DiffusionTrainConfig, TINY_MOST, overrides)
    assert row_mean_key(cfg, "stage1") == "x0_u"
    assert torch.equal(row_mean(cfg, "x0_u"), row_mean(plain, "x0_u"))  # stage 1's mean start: the mean of P_u
