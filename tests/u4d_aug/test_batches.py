"""u4d_aug.batches: azimuth crops wrap around the ring; a step's batch and noise depend on (seed, step, rank) only."""

from __future__ import annotations

import torch

from tests.tiny_nets import diffusion_config
from tests.tiny_worlds import write_tiny_world
from u4d_aug.batches import RangeImages, crop_batch, training_batch


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
