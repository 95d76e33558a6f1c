"""`u4d train-diffusion stage=u4d`: one net for both U4D stages (task embedding), both tasks in every batch, and
two-stage sampling from that one net; the crop margin, the cosine lr and v-prediction of the training recipe."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import PLAIN_SAMPLING, diffusion_config, gen_config, plain_settings
from tests.tiny_worlds import write_tiny_world
from u4d_aug.batches import RangeImages, crop_loss_weight, net_row_mean, stage_inputs, training_batch
from u4d_aug.config import load_config
from u4d_aug.diffusion import (
    STAGE1_TASK,
    STAGE2_TASK,
    GaussianDiffusion,
    _mean_per_sample,
    empty_condition,
    eps_from_v,
    stage1_count,
)
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, _checkpoint_paths, generate_bank
from u4d_aug.pipeline import generate_u4d, load_generator
from u4d_aug.stage import DiffusionOptimConfig, build_net
from u4d_aug.train import learning_rate, train


@pytest.fixture
def tiny_world(tmp_path: Path) -> tuple[Path, Path]:
    root, probs_root = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(root, probs_root)
    return root, probs_root


def _perturbed(net: torch.nn.Module) -> torch.nn.Module:
    """The net with its zero-initialised tensors (output convs, residual outputs) drawn at random: an untrained net
    would give ε̂ = 0 whatever its input."""
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for param in net.parameters():
            if not bool(param.any()):
                param.copy_(0.1 * torch.randn(param.shape, generator=generator))
    return net


def test_u4d_net_has_both_heads_and_the_stage_embedding_changes_its_output(tiny_world, tmp_path):
    cfg = diffusion_config(tiny_world, tmp_path / "run", "u4d")
    assert (cfg.net.mask_head, cfg.net.cond_channels, cfg.net.num_tasks) == (True, 3, 2)
    net = _perturbed(build_net(cfg)).eval()
    x_t = torch.randn(2, 2, cfg.height, cfg.width, generator=torch.Generator().manual_seed(0))
    cond = empty_condition(torch.zeros(2, 2, cfg.height, cfg.width))
    lam = torch.zeros(2)
    with torch.no_grad():
        eps1, mask1 = net(x_t, lam, cond, task=STAGE1_TASK)
        eps2, mask2 = net(x_t, lam, cond, task=STAGE2_TASK)
    assert mask1 is not None and mask2 is not None
    assert not torch.allclose(eps1, eps2)  # same input, other stage: another output
    with pytest.raises(ValueError, match="needs task"):
        net(x_t, lam, cond)


def test_every_u4d_batch_trains_both_tasks_and_one_set_of_weights(tiny_world, tmp_path):
    cfg = diffusion_config(tiny_world, tmp_path / "run", "u4d", "batch_size=4")
    images = RangeImages(cfg)
    batch, offsets, generator = training_batch(images, cfg, 0, 0, torch.device("cpu"))
    assert torch.equal(batch["x0_u"], torch.where(batch["m_u"].bool(), batch["x0"], -torch.ones_like(batch["x0"])))
    net = _perturbed(build_net(cfg))
    diffusion = GaussianDiffusion(net, cfg.diffusion)
    seen: list[torch.Tensor] = []
    net.task_embed.register_forward_hook(lambda module, args, out: seen.append(args[0].clone()))
    losses = diffusion(*stage_inputs("u4d", batch), generator, offsets)
    assert seen[0].tolist() == [STAGE1_TASK, STAGE1_TASK, STAGE2_TASK, STAGE2_TASK]  # both tasks, one forward
    assert {"eps_mse_stage1", "eps_mse_stage2", "mask_bce"} <= set(losses)

    # a stage-1-only step and a stage-2-only step move the same shared weights (not two nets' halves)
    grads = {}
    for task in (STAGE1_TASK, STAGE2_TASK):
        net.zero_grad()
        x_t = torch.randn(2, 2, cfg.height, cfg.width, generator=torch.Generator().manual_seed(2))
        cond = stage_inputs("u4d", batch)[1][:2]
        full_cond = torch.cat([cond, batch["m_u"][:2]], dim=1)
        eps, _ = net(x_t, torch.zeros(2), full_cond, task=task)
        eps.square().mean().backward()
        grads[task] = {name: p.grad.clone() for name, p in net.named_parameters() if p.grad is not None}
    shared = [name for name in grads[STAGE1_TASK] if name in grads[STAGE2_TASK] and "task_embed" not in name]
    assert len(shared) == len([n for n, _ in net.named_parameters() if "task_embed" not in n and "mask_conv" not in n])
    assert all(
        grads[STAGE1_TASK][n].abs().sum() > 0 and grads[STAGE2_TASK][n].abs().sum() > 0 for n in ("stem.weight",)
    )


def test_u4d_stage_trains_checkpoints_and_samples_two_stages_from_one_net(tiny_world, tmp_path):
    out = tmp_path / "run"
    record = train(diffusion_config(tiny_world, out, "u4d", "diffusion.cond_noise=0.05"), progress=False)
    assert record["step"] == 4 and np.isfinite(record["loss"]) and np.isfinite(record["mask_bce"])
    loaded = load_generator(out)
    assert loaded.config.diffusion.stage == "u4d"
    result = generate_u4d(loaded, loaded, 2, torch.Generator().manual_seed(0), plain_settings(2, "ddpm"))
    assert result["x0"].shape == (2, 2, 16, 64)
    outside = result["m_u_pred"].expand_as(result["x0_u"]) == 0
    assert bool((result["x0_u"][outside] == -1).all())  # stage 1's region, empty off its mask
    # `u4d generate net=RUN`: the one net serves both stages; the bank records it under both roles
    bank = tmp_path / "bank"
    overrides = [f"net={out}", "num=2", "sampler=ddpm", "steps=2", *PLAIN_SAMPLING, "device=cpu", "batch_size=2"]
    cfg = load_config(GenerateConfig, None, overrides)
    manifest = generate_bank(cfg, bank, progress=False)
    assert manifest["complete"] and manifest["checkpoints"]["stage1"] == manifest["checkpoints"]["stage2"]
    with pytest.raises(InputError, match="net: a one-net u4d checkpoint replaces stage1 and stage2"):
        generate_bank(gen_config({"stage1": out, "stage2": out, "baseline": out}, f"net={out}"), tmp_path / "b2")
    # a preset's default `net` does not stop baseline mode, which reads `baseline` only
    as_baseline = load_config(GenerateConfig, None, [*overrides, "mode=baseline", f"baseline={out}"])
    assert _checkpoint_paths(as_baseline) == {"baseline": sorted((out / "checkpoints").glob("step_*.pt"))[-1]}


def test_u4d_needs_two_samples_per_batch(tiny_world, tmp_path):
    assert stage1_count(4, 0.5) == 2 and stage1_count(2, 0.9) == 1 and stage1_count(3, 0.1) == 1
    with pytest.raises(InputError, match="batch_size must be >= 2"):
        diffusion_config(tiny_world, tmp_path / "run", "u4d", "batch_size=1")


def test_crop_margin_takes_the_crop_edges_out_of_the_loss(tiny_world, tmp_path):
    cfg = diffusion_config(tiny_world, tmp_path / "run", "baseline", "crop_width=32", "crop_margin=4")
    weight = crop_loss_weight(cfg, torch.device("cpu"))
    assert weight.tolist() == [0.0] * 4 + [1.0] * 24 + [0.0] * 4
    # the losses are the weighted mean over the kept columns: what the margin columns hold adds nothing
    values = torch.rand(2, 2, 16, 32)
    spoiled = values.clone()
    spoiled[..., :4] = 1e6
    torch.testing.assert_close(_mean_per_sample(spoiled, weight), values[..., 4:28].flatten(1).mean(dim=1))
    net = _perturbed(build_net(cfg))
    diffusion = GaussianDiffusion(net, cfg.diffusion)
    x0 = torch.rand(2, 2, 16, 32) * 2 - 1
    offsets = torch.tensor([0, 8])
    with_margin = diffusion(x0, generator=torch.Generator().manual_seed(0), crop_offsets=offsets, loss_weight=weight)
    without = diffusion(x0, generator=torch.Generator().manual_seed(0), crop_offsets=offsets)
    assert float(with_margin["loss"].detach()) != float(without["loss"].detach())
    with pytest.raises(InputError, match="crop_margin"):
        diffusion_config(tiny_world, tmp_path / "run", "baseline", "crop_width=32", "crop_margin=8")


def test_cosine_lr_decays_to_its_floor_by_steps_or_by_the_clock():
    cfg = DiffusionOptimConfig(lr=1.0, warmup_steps=10, schedule="cosine", min_lr_ratio=0.1)
    assert learning_rate(0, cfg, 110) == pytest.approx(0.1)
    assert learning_rate(10, cfg, 110) == pytest.approx(1.0)
    assert learning_rate(59, cfg, 110) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 49 / 99)))
    assert learning_rate(109, cfg, 110) == pytest.approx(0.1)
    assert learning_rate(20, cfg, 110, time_fraction=1.0) == pytest.approx(0.1)  # the wall-clock budget is used
    constant = DiffusionOptimConfig(lr=1.0, warmup_steps=10)
    assert learning_rate(100, constant, 110) == 1.0


def test_v_prediction_converts_back_to_the_eps_of_the_same_x_t():
    x0 = torch.rand(3, 2, 4, 8) * 2 - 1
    eps = torch.randn(3, 2, 4, 8, generator=torch.Generator().manual_seed(0))
    lam = torch.tensor([-3.0, 0.0, 4.0])
    alpha, sigma = torch.sigmoid(lam).sqrt().view(3, 1, 1, 1), torch.sigmoid(-lam).sqrt().view(3, 1, 1, 1)
    x_t = alpha * x0 + sigma * eps
    v = alpha * eps - sigma * x0
    torch.testing.assert_close(eps_from_v(x_t, lam, v), eps)


def test_v_parameterized_u4d_net_trains_and_samples(tiny_world, tmp_path):
    out = tmp_path / "run"
    train(diffusion_config(tiny_world, out, "u4d", "diffusion.parameterization=v"), progress=False)
    loaded = load_generator(out)
    result = generate_u4d(loaded, loaded, 1, torch.Generator().manual_seed(0), plain_settings(2, "dpmpp2m-sde"))
    assert bool(torch.isfinite(result["x0"]).all())


def test_row_means_of_a_u4d_net_with_condition_noise(tiny_world, tmp_path):
    cfg = diffusion_config(tiny_world, tmp_path / "run", "u4d", "diffusion.cond_noise=0.05")
    mean_x0, source_x0 = net_row_mean(cfg, role="stage2")
    mean_u, source_u = net_row_mean(cfg, role="stage1")
    assert (source_x0["key"], source_u["key"]) == ("x0", "x0_u")
    assert mean_x0.shape == mean_u.shape == (2, 16, 1)
    assert float(mean_u.mean()) < float(mean_x0.mean())  # x0_u is empty (-1) off the uncertain region
