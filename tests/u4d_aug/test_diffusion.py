"""Cosine log-SNR schedule, Min-SNR weights, stage losses (ε-MSE, stage-1 mask BCE), a stage-2 overfit."""

from __future__ import annotations

import math

import pytest
import torch

from u4d_aug.diffusion import (
    LOG_SNR_MAX,
    LOG_SNR_MIN,
    DiffusionConfig,
    GaussianDiffusion,
    alpha_sigma,
    log_snr,
    min_snr_weight,
    noisy_condition,
    stage_cond,
)
from u4d_aug.errors import InputError
from u4d_aug.nn.unet import RangeUNet, UNetConfig
from u4d_aug.sampling import ddim_sample

H, W = 16, 64


def tiny_net(**overrides) -> RangeUNet:
    base = dict(
        base_channels=8,
        channel_multipliers=(1, 2),
        num_res_blocks=1,
        attention=False,
        fourier_features=False,
        gn_groups=4,
    )
    base.update(overrides)
    cfg = UNetConfig(**base)
    if cfg.fourier_features:
        return RangeUNet(cfg, torch.linspace(0.05, -0.4, H), torch.linspace(3.1, -3.1, W))
    return RangeUNet(cfg)


def toy_scan() -> torch.Tensor:
    """(1, 2, 16, 64) range image in [-1, 1]: ground rows, a box, a no-return gap (-1)."""
    rows = torch.linspace(0, 1, H)[:, None]
    cols = torch.linspace(0, 2 * math.pi, W + 1)[None, :-1]
    depth = (0.8 - 0.9 * rows + 0.1 * torch.sin(3 * cols)).expand(H, W).clone()
    depth[4:9, 20:30] = -0.2
    reflectance = (0.3 * torch.cos(2 * cols) + 0.2 * rows - 0.4).expand(H, W).clone()
    x0 = torch.stack([depth, reflectance])
    x0[:, :2, 40:50] = -1.0
    return x0.clamp(-1, 1)[None]


def test_schedule_identities_and_golden_values():
    t = torch.linspace(0, 1, 1001, dtype=torch.float64)
    lam = log_snr(t)
    alpha, sigma = alpha_sigma(lam)
    assert torch.allclose(alpha.square() + sigma.square(), torch.ones_like(t), atol=1e-12)
    assert (lam.diff() < 0).all()  # log-SNR strictly decreasing in t
    assert (alpha.square().diff() < 0).all()  # ᾱ = α² decreasing, σ² increasing
    assert math.isclose(lam[0].item(), LOG_SNR_MAX, abs_tol=1e-9)
    assert math.isclose(lam[-1].item(), LOG_SNR_MIN, abs_tol=1e-9)
    assert math.isclose(log_snr(torch.tensor(0.5, dtype=torch.float64)).item(), 0.0, abs_tol=1e-12)
    assert torch.allclose(lam, -lam.flip(0), atol=1e-9)  # cosine schedule is symmetric about t = 1/2
    a, s = alpha_sigma(torch.tensor(0.0))
    assert math.isclose(a.item(), math.sqrt(0.5), rel_tol=1e-6) and math.isclose(s.item(), math.sqrt(0.5), rel_tol=1e-6)
    lam32 = log_snr(torch.linspace(0, 1, 1001))  # float32 stays finite at the ends
    assert torch.isfinite(lam32).all() and (lam32.diff() <= 0).all()


def test_min_snr_weight():
    lam = torch.tensor([math.log(5.0), math.log(50.0), math.log(0.5), -15.0])
    weight = min_snr_weight(lam, 5.0)
    assert torch.allclose(weight, torch.tensor([1.0, 0.1, 1.0, 1.0]), atol=1e-6)  # min(SNR, 5) / SNR
    assert torch.equal(min_snr_weight(lam, None), torch.ones(4))


def test_untrained_loss_is_unit_noise_power(generator):
    """Zero-init net predicts ε̂ = 0, so the unweighted ε-MSE is E[ε²] = 1."""
    diffusion = GaussianDiffusion(tiny_net(), DiffusionConfig(stage="baseline", min_snr_gamma=None))
    losses = diffusion(torch.zeros(4, 2, H, W), generator=generator)
    assert set(losses) == {"loss", "eps_mse"}
    assert math.isclose(losses["loss"].item(), 1.0, abs_tol=0.05)
    assert losses["loss"].requires_grad and not losses["eps_mse"].requires_grad


def test_same_generator_same_loss_different_generator_different():
    diffusion = GaussianDiffusion(tiny_net(), DiffusionConfig(stage="baseline"))
    x0 = toy_scan().expand(2, -1, -1, -1)
    a = diffusion(x0, generator=torch.Generator().manual_seed(3))["loss"]
    b = diffusion(x0, generator=torch.Generator().manual_seed(3))["loss"]
    c = diffusion(x0, generator=torch.Generator().manual_seed(4))["loss"]
    assert a.item() == b.item() and a.item() != c.item()


def test_sequences_share_t_per_sample(generator):
    """Every frame of sample b is noised to the same t_b and the net embeds log-SNR(t_b) for each of its frames."""
    net = tiny_net(cond_channels=3)
    diffusion = GaussianDiffusion(net, DiffusionConfig(stage="stage2"))
    x0 = torch.rand(2, 3, 2, H, W, generator=generator) * 2 - 1  # (B, L, C, H, W)
    seen = {}

    def record(name: str):
        def hook(module, args) -> None:  # a pre-hook that returns nothing leaves the call unchanged
            seen[name] = args[0].clone()

        return hook

    net.register_forward_pre_hook(record("x_t"))
    net.embed.register_forward_pre_hook(record("log_snr"))
    losses = diffusion(x0, x0.clone(), torch.ones(2, 3, 1, H, W), generator=torch.Generator().manual_seed(5))
    assert torch.isfinite(losses["loss"])
    replay = torch.Generator().manual_seed(5)  # forward draws t (B,), then ε of x0's shape
    t = torch.rand(2, generator=replay)
    eps = torch.randn(x0.shape, generator=replay)
    alpha, sigma = alpha_sigma(log_snr(t).view(2, 1, 1, 1, 1))
    torch.testing.assert_close(seen["x_t"], alpha * x0 + sigma * eps)  # (B, L, C, H, W): one α, σ per sample
    assert seen["log_snr"].shape == (6,)  # (B·L,): frames folded into the batch, sample-major
    torch.testing.assert_close(seen["log_snr"].view(2, 3), log_snr(t)[:, None].expand(2, 3))
    assert float((log_snr(t)[0] - log_snr(t)[1]).abs()) > 0.1  # the two samples have their own t


def test_stage_checks():
    with pytest.raises(InputError, match="mask_head"):
        GaussianDiffusion(tiny_net(), DiffusionConfig(stage="stage1"))
    with pytest.raises(InputError, match="cond_channels=3"):
        GaussianDiffusion(tiny_net(cond_channels=2), DiffusionConfig(stage="stage2"))
    stage2 = GaussianDiffusion(tiny_net(cond_channels=3), DiffusionConfig(stage="stage2"))
    with pytest.raises(ValueError, match="m_u"):
        stage2(torch.zeros(1, 2, H, W), cond=torch.zeros(1, 2, H, W))
    stage1 = GaussianDiffusion(tiny_net(mask_head=True), DiffusionConfig(stage="stage1"))
    with pytest.raises(ValueError, match="m_u"):
        stage1(torch.zeros(1, 2, H, W))
    with pytest.raises(InputError, match="stage"):
        DiffusionConfig(stage="stage3")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="min_snr_gamma"):
        DiffusionConfig(min_snr_gamma=0.0)
    with pytest.raises(InputError, match="cond_noise"):
        DiffusionConfig(stage="stage1", cond_noise=0.1)
    with pytest.raises(InputError, match="cond_noise"):
        DiffusionConfig(stage="stage2", cond_noise=-0.1)
    for bad in (0.0, 1.5):
        with pytest.raises(InputError, match="train_t_max"):
            DiffusionConfig(train_t_max=bad)


def test_train_t_max_draws_only_the_low_noise_end_and_1_changes_nothing():
    net = tiny_net()
    seen: list[torch.Tensor] = []
    forward = net.forward
    net.forward = lambda x_t, lam, cond: seen.append(lam) or forward(x_t, lam, cond)  # type: ignore[method-assign]
    x0 = toy_scan().expand(64, -1, -1, -1)
    losses = {}
    for t_max in (1.0, 0.1):
        diffusion = GaussianDiffusion(net, DiffusionConfig(train_t_max=t_max))
        losses[t_max] = float(diffusion(x0, generator=torch.Generator().manual_seed(0))["eps_mse"])
    assert seen[0].min() < 0.0 < seen[0].max()  # the whole schedule
    assert float(seen[1].min()) >= float(log_snr(torch.tensor(0.1))) - 1e-5  # log-SNR >= 3.7 only
    assert torch.allclose(log_snr(torch.rand(64, generator=torch.Generator().manual_seed(0))), seen[0])  # as before
    assert losses[0.1] < losses[1.0]  # Min-SNR weights are small at high SNR


def test_input_perturbation_adds_sigma_gamma_noise_to_the_net_input_and_keeps_the_eps_target():
    net = tiny_net()
    seen: list[torch.Tensor] = []
    net.register_forward_pre_hook(lambda module, args: seen.append(args[0].clone()))
    x0 = toy_scan().expand(8, -1, -1, -1)
    losses = {}
    for gamma in (0.0, 0.3):
        diffusion = GaussianDiffusion(net, DiffusionConfig(input_perturbation=gamma))
        losses[gamma] = diffusion(x0, generator=torch.Generator().manual_seed(5))["eps_mse"]
    plain = GaussianDiffusion(net, DiffusionConfig())(x0, generator=torch.Generator().manual_seed(5))["eps_mse"]
    assert torch.equal(losses[0.0], plain)  # off: the very same draws and loss
    generator = torch.Generator().manual_seed(5)  # redraw what the loss drew: t, ε, then ξ
    t = torch.rand(8, generator=generator)
    eps = torch.randn(x0.shape, generator=generator)
    xi = torch.randn(x0.shape, generator=generator)
    alpha, sigma = alpha_sigma(log_snr(t).view(8, 1, 1, 1))
    assert torch.allclose(seen[0], alpha * x0 + sigma * eps, atol=1e-6)
    assert torch.allclose(seen[1], alpha * x0 + sigma * (eps + 0.3 * xi), atol=1e-6)  # σ γ ξ on the input only
    with torch.no_grad():
        pred = net(seen[1], log_snr(t))[0]
    weight = min_snr_weight(log_snr(t), 5.0)
    assert torch.allclose(losses[0.3], (weight * (pred - eps).square().mean(dim=(1, 2, 3))).mean(), atol=1e-6)
    for bad in (-0.1, 1.0):
        with pytest.raises(InputError, match="input_perturbation"):
            DiffusionConfig(input_perturbation=bad)


def test_noisy_condition_touches_only_the_uncertain_region():
    x0 = toy_scan().expand(3, -1, -1, -1)  # (3, 2, H, W)
    m_u = torch.zeros(3, 1, H, W)
    m_u[:, :, 4:9, 10:40] = 1.0
    x0_u = torch.where(m_u.bool().expand_as(x0), x0, torch.full_like(x0, -1.0))
    noisy = noisy_condition(x0_u, m_u, 0.3, torch.Generator().manual_seed(0))
    inside = m_u.bool().expand_as(x0_u)
    assert torch.equal(noisy[~inside], x0_u[~inside])  # empty pixels stay empty
    assert float(noisy.abs().max()) <= 1.0
    change = (noisy - x0_u)[inside].view(3, -1)
    assert bool((change.abs().amax(dim=1) > 0).all()) and float(change.std(dim=1).max()) <= 0.3 + 0.05
    assert not torch.allclose(change.std(dim=1)[0], change.std(dim=1)[1])  # a noise level per sample
    assert torch.equal(noisy, noisy_condition(x0_u, m_u, 0.3, torch.Generator().manual_seed(0)))
    assert torch.equal(noisy_condition(x0_u, m_u, 0.0, torch.Generator().manual_seed(0)), x0_u)


def test_stage2_cond_noise_reaches_the_net_and_zero_changes_nothing():
    torch.manual_seed(0)
    net = tiny_net(cond_channels=3)
    seen: list[torch.Tensor] = []
    net.register_forward_pre_hook(lambda module, args: seen.append(args[2].clone()))
    x0 = toy_scan()
    m_u = torch.zeros(1, 1, H, W)
    m_u[:, :, 4:9, 20:30] = 1.0
    x0_u = torch.where(m_u.bool().expand_as(x0), x0, torch.full_like(x0, -1.0))
    losses = {}
    for noise in (0.0, 0.5):
        diffusion = GaussianDiffusion(net, DiffusionConfig(stage="stage2", cond_noise=noise))
        losses[noise] = diffusion(x0, cond=x0_u, m_u=m_u, generator=torch.Generator().manual_seed(3))["loss"]
    plain = GaussianDiffusion(net, DiffusionConfig(stage="stage2"))(
        x0, cond=x0_u, m_u=m_u, generator=torch.Generator().manual_seed(3)
    )["loss"]
    assert torch.equal(losses[0.0], plain)  # off: the very same loss
    assert torch.equal(seen[0], stage_cond(x0_u, m_u))
    noisy = seen[1]
    assert not torch.equal(noisy[:, :2], x0_u) and torch.equal(noisy[:, 2:], m_u)  # values perturbed, mask kept


def test_stage1_mask_bce_present_and_decreasing():
    torch.manual_seed(0)
    diffusion = GaussianDiffusion(tiny_net(mask_head=True), DiffusionConfig(stage="stage1", mask_weight=1.0))
    x0 = toy_scan()
    m_u = torch.zeros(2, 1, H, W)
    m_u[:, :, 4:9, 20:30] = 1.0  # the "uncertain" box
    x0_u = torch.where(m_u.bool(), x0, torch.full_like(x0, -1.0))
    optimizer = torch.optim.Adam(diffusion.parameters(), lr=3e-3)
    generator = torch.Generator().manual_seed(0)
    history = []
    for _ in range(40):
        losses = diffusion(x0_u, m_u=m_u, generator=generator)
        history.append(losses["mask_bce"].item())
        optimizer.zero_grad()
        losses["loss"].backward()
        optimizer.step()
    assert math.isclose(history[0], math.log(2.0), rel_tol=1e-5)  # zero-init logits: BCE = log 2
    assert sum(history[-5:]) / 5 < 0.6 * history[0]


def test_stage2_overfits_one_scan_and_reconstructs_it():
    """Stage 2 trained on ONE 16×64 scan regenerates it (DDIM from noise + condition): error ≪ untrained."""
    torch.manual_seed(0)
    x0 = toy_scan()
    m_u = (torch.rand(1, 1, H, W, generator=torch.Generator().manual_seed(0)) < 0.15).float()
    x0_u = torch.where(m_u.bool(), x0, torch.full_like(x0, -1.0))
    net = tiny_net(base_channels=16, cond_channels=3, fourier_features=True)
    diffusion = GaussianDiffusion(net, DiffusionConfig(stage="stage2"))

    def reconstruction_error() -> float:
        net.eval()
        sample = ddim_sample(net, (1, 2, H, W), 16, torch.Generator().manual_seed(1), cond=stage_cond(x0_u, m_u))
        net.train()
        return (sample.x0 - x0).abs().mean().item()

    untrained = reconstruction_error()
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    generator = torch.Generator().manual_seed(2)
    batch = [t.expand(4, -1, -1, -1) for t in (x0, x0_u, m_u)]
    for _ in range(150):
        loss = diffusion(batch[0], batch[1], batch[2], generator=generator)["loss"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    trained = reconstruction_error()
    assert untrained > 0.5
    assert trained < 0.25 * untrained, (untrained, trained)  # measured: 0.998 -> 0.100
