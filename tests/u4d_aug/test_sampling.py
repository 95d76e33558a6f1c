"""DDPM / DDIM / DPM-Solver++(2M) and 2M SDE samplers (one signature, generator in, extra out)."""

from __future__ import annotations

import math

import pytest
import torch

from u4d_aug.diffusion import LOG_SNR_MAX, LOG_SNR_MIN, alpha_sigma, log_snr
from u4d_aug.nn.unet import RangeUNet, UNetConfig
from u4d_aug.sampling import (
    ddim_sample,
    ddpm_sample,
    dpmpp_2m_sample,
    dpmpp_2m_sde_sample,
    mean_start,
    replace_known,
    sample,
)

SAMPLERS = [ddpm_sample, ddim_sample, dpmpp_2m_sample, dpmpp_2m_sde_sample]
SHAPE = (2, 2, 8, 16)


def oracle(x0: torch.Tensor):
    """A perfect denoiser for a single known x0: ε = (x_t − α x0) / σ; returns (ε, log_snr) as its extra."""

    def denoise(x_t: torch.Tensor, lam: torch.Tensor, cond: torch.Tensor | None):
        alpha, sigma = alpha_sigma(lam.double().view(-1, 1, 1, 1))
        return ((x_t.double() - alpha * x0.double()) / sigma).float(), lam

    return denoise


def two_point(a: torch.Tensor):
    """The exact denoiser of data x0 = ±a with probability ½ each: E[x0 | x_t] = a tanh(α <x_t, a> / σ²) per sample."""

    def denoise(x_t: torch.Tensor, lam: torch.Tensor, cond: torch.Tensor | None):
        alpha, sigma = alpha_sigma(lam.double().view(-1, 1, 1, 1))
        x = x_t.double()
        score = (x * a.double()).sum(dim=(1, 2, 3), keepdim=True)  # (B, 1, 1, 1) <x_t, a>
        x0 = a.double() * torch.tanh(alpha * score / sigma**2)
        return ((x - alpha * x0) / sigma).float()

    return denoise


def random_net(most: bool = False) -> RangeUNet:
    cfg = UNetConfig(
        base_channels=8,
        channel_multipliers=(1, 2),
        num_res_blocks=1,
        attention=False,
        fourier_features=False,
        gn_groups=4,
        mask_head=True,
        most=most,
    )
    net = RangeUNet(cfg)
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=generator) * 0.2)
    return net.eval()


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_same_generator_same_sample_different_generator_different(sampler):
    net = random_net()
    a = sampler(net, SHAPE, 4, torch.Generator().manual_seed(7)).x0
    b = sampler(net, SHAPE, 4, torch.Generator().manual_seed(7)).x0
    c = sampler(net, SHAPE, 4, torch.Generator().manual_seed(8)).x0
    assert torch.equal(a, b)
    assert not torch.allclose(a, c)
    assert a.shape == SHAPE and a.min() >= -1 and a.max() <= 1  # x̂0 clamped to [-1, 1]


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_one_generator_per_element_gives_the_batch_of_one_samples(sampler):
    net = random_net()
    seeds = [3, 4, 5]
    batched = sampler(net, (3, *SHAPE[1:]), 4, [torch.Generator().manual_seed(s) for s in seeds])
    for i, seed in enumerate(seeds):
        alone = sampler(net, (1, *SHAPE[1:]), 4, torch.Generator().manual_seed(seed))
        torch.testing.assert_close(batched.x0[i : i + 1], alone.x0, atol=1e-5, rtol=0)
        torch.testing.assert_close(batched.extra[i : i + 1], alone.extra, atol=1e-4, rtol=0)  # mask logits
    assert not torch.allclose(batched.x0[0], batched.x0[1], atol=0.1)
    with pytest.raises(ValueError, match="2 generators for a batch of 3"):
        sampler(net, (3, *SHAPE[1:]), 4, [torch.Generator(), torch.Generator()])


@pytest.mark.parametrize("sampler", SAMPLERS)
@pytest.mark.parametrize("steps", [1, 8, 64])
def test_perfect_denoiser_recovers_x0(sampler, steps):
    x0 = torch.rand(SHAPE, generator=torch.Generator().manual_seed(1)) * 1.8 - 0.9
    sample = sampler(oracle(x0), SHAPE, steps, torch.Generator().manual_seed(2))
    # one step divides by alpha(t=1) ~ 5.5e-4, which magnifies float32 rounding of ε̂ about 2000 times
    assert torch.allclose(sample.x0, x0, atol=1e-3 if steps == 1 else 1e-5)


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_log_snr_grid_and_last_extra(sampler):
    """The denoiser sees log-SNR (B,) rising from −15; the last call's extra comes back with the sample."""
    x0 = torch.zeros(SHAPE)
    steps = 5
    sample = sampler(oracle(x0), SHAPE, steps, torch.Generator().manual_seed(0))
    expected_last = log_snr(torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64))[steps - 1].item()
    assert sample.extra.shape == (SHAPE[0],)
    assert torch.allclose(sample.extra, torch.full((SHAPE[0],), expected_last))
    assert LOG_SNR_MIN < expected_last < LOG_SNR_MAX


def test_stage1_style_denoiser_returns_mask_logits_and_plain_eps_returns_none():
    net = random_net()
    x0, logits = ddim_sample(net, SHAPE, 3, torch.Generator().manual_seed(0))
    assert logits.shape == (SHAPE[0], 1, *SHAPE[2:])
    plain = ddim_sample(lambda x, lam, cond: torch.zeros_like(x), SHAPE, 3, torch.Generator().manual_seed(0))
    assert plain.extra is None


def test_condition_is_passed_and_ddim_is_deterministic_given_x1():
    seen = []

    def denoise(x_t, lam, cond):
        seen.append(cond)
        return torch.zeros_like(x_t)

    cond = torch.ones(SHAPE)
    ddim_sample(denoise, SHAPE, 3, torch.Generator().manual_seed(0), cond=cond, device="cpu")
    assert len(seen) == 3 and all(c is cond for c in seen)
    with pytest.raises(ValueError, match="steps"):
        ddpm_sample(denoise, SHAPE, 0, torch.Generator())


def test_ddim_draws_only_x1_ddpm_draws_fresh_noise_per_step():
    """Generator use: DDIM, 2M and 2M SDE at η = 0 draw x_1 only; ancestral DDPM and 2M SDE draw x_1 and one noise
    per step but the last."""
    zero = lambda x, lam, cond: torch.zeros_like(x)  # noqa: E731
    steps = 6
    cases = (
        (ddim_sample, {}, 1),
        (dpmpp_2m_sample, {}, 1),
        (dpmpp_2m_sde_sample, {"eta": 0.0}, 1),
        (ddpm_sample, {}, steps),
        (dpmpp_2m_sde_sample, {}, steps),
    )
    for sampler, kwargs, draws in cases:
        used = torch.Generator().manual_seed(5)
        sampler(zero, SHAPE, steps, used, **kwargs)
        reference = torch.Generator().manual_seed(5)
        for _ in range(draws):
            torch.randn(SHAPE, generator=reference)
        assert torch.equal(used.get_state(), reference.get_state()), (sampler.__name__, kwargs)


# --- orders of accuracy on a toy Gaussian whose probability-flow ODE is solved in closed form -------------

MU, S = 0.3, 0.2  # x0 ~ N(μ, s²), every element of the tensor independently
TOY_SHAPE = (4, 1, 1, 256)


def gaussian_eps(x_t: torch.Tensor, lam: torch.Tensor, cond: torch.Tensor | None) -> torch.Tensor:
    """Exact ε̂ = E[ε | x_t] = σ (x_t − α μ) / (α² s² + σ²), in float64 so the samplers run in float64."""
    alpha, sigma = alpha_sigma(lam.double().view(-1, 1, 1, 1))
    return sigma * (x_t.double() - alpha * MU) / (alpha**2 * S**2 + sigma**2)


def toy_errors(sampler, steps_list: tuple[int, ...], **kwargs) -> list[float]:
    """RMS distance of the sample to the ODE's exact end x0* = μ + s (x_1 − α_1 μ) / sqrt(α_1² s² + σ_1²)."""
    x1 = torch.randn(TOY_SHAPE, generator=torch.Generator().manual_seed(0)).double()  # the samplers' own x_1
    alpha, sigma = alpha_sigma(torch.tensor(LOG_SNR_MIN, dtype=torch.float64))
    x0_star = MU + S * (x1 - alpha * MU) / torch.sqrt(alpha**2 * S**2 + sigma**2)
    errors = []
    for steps in steps_list:
        x0 = sampler(gaussian_eps, TOY_SHAPE, steps, torch.Generator().manual_seed(0), clip=False, **kwargs).x0
        errors.append((x0 - x0_star).pow(2).mean().sqrt().item())
    return errors


def orders(errors: list[float]) -> list[float]:
    """Observed orders log2(e_n / e_2n) of errors at step counts doubling from one to the next."""
    return [math.log2(a / b) for a, b in zip(errors, errors[1:])]


def test_ddim_is_first_order_and_dpmpp_2m_second_order():
    """Measured RMS errors: DDIM 5.8e-2, 3.1e-2, 1.6e-2 at 10/20/40 steps; 2M on the log-SNR grid 2.6e-3,
    6.9e-4, 1.8e-4 at 32/64/128 (orders 1.90, 1.98).

    2M's order is measured on the log-SNR grid: on the cosine time grid the last steps near t = 0 stay O(1)
    wide in λ whatever the step count, so on this narrow toy (s = 0.2) 2M nears order 2 only past ~256 steps.
    """
    ddim = orders(toy_errors(ddim_sample, (10, 20, 40)))
    assert all(0.8 < p < 1.2 for p in ddim), ddim
    dpm = orders(toy_errors(dpmpp_2m_sample, (32, 64, 128), grid="logsnr"))
    assert all(p > 1.7 for p in dpm), dpm


def test_dpmpp_2m_beats_ddim_at_the_same_steps():
    """Measured at 8/16/32 steps: DDIM 7.1e-2, 3.8e-2, 2.0e-2; 2M time grid 6.3e-2, 2.1e-2, 2.2e-3; log-SNR grid
    7.4e-3, 7.3e-3, 2.6e-3."""
    steps = (8, 16, 32)
    ddim = toy_errors(ddim_sample, steps)
    for grid in ("time", "logsnr"):
        dpm = toy_errors(dpmpp_2m_sample, steps, grid=grid)
        assert all(d < e for d, e in zip(dpm, ddim)), (grid, dpm, ddim)
        assert dpm[-1] < ddim[-1] / 5, (grid, dpm, ddim)


def test_dpmpp_2m_starts_as_ddim():
    """One step returns the same x̂0; two steps: the first update is first order, i.e. DDIM's, in another form."""
    net = random_net()
    one = dpmpp_2m_sample(net, SHAPE, 1, torch.Generator().manual_seed(3))
    assert torch.equal(one.x0, ddim_sample(net, SHAPE, 1, torch.Generator().manual_seed(3)).x0)
    two = dpmpp_2m_sample(gaussian_eps, TOY_SHAPE, 2, torch.Generator().manual_seed(3), clip=False)
    ddim_two = ddim_sample(gaussian_eps, TOY_SHAPE, 2, torch.Generator().manual_seed(3), clip=False)
    torch.testing.assert_close(two.x0, ddim_two.x0, atol=1e-7, rtol=0)  # 2M scales the float32 x_1 in float32


def test_dispatcher_picks_by_name_and_grid_and_rejects_unknown_names():
    zero = lambda x, lam, cond: torch.zeros_like(x)  # noqa: E731
    cases = [("ddpm", ddpm_sample, "time"), ("ddim", ddim_sample, "time")]
    cases += [(name, f, grid) for name, f in (("dpmpp2m", dpmpp_2m_sample), ("dpmpp2m-sde", dpmpp_2m_sde_sample))
              for grid in ("time", "logsnr")]  # fmt: skip
    for name, sampler, grid in cases:
        picked = sample(name, gaussian_eps, TOY_SHAPE, 3, torch.Generator().manual_seed(1), clip=False, grid=grid)
        kwargs = {} if sampler in (ddpm_sample, ddim_sample) else {"grid": grid}
        direct = sampler(gaussian_eps, TOY_SHAPE, 3, torch.Generator().manual_seed(1), clip=False, **kwargs)
        assert torch.equal(picked.x0, direct.x0), (name, grid)
    with pytest.raises(ValueError, match="'euler' is not one of 'ddpm', 'ddim', 'dpmpp2m', 'dpmpp2m-sde'"):
        sample("euler", zero, SHAPE, 3, torch.Generator())
    with pytest.raises(ValueError, match="grid 'karras' is not one of 'time', 'logsnr'"):
        dpmpp_2m_sample(zero, SHAPE, 3, torch.Generator(), grid="karras")
    for name in ("ddpm", "ddim"):
        with pytest.raises(ValueError, match=f"only by the samplers 'dpmpp2m', 'dpmpp2m-sde'; '{name}' runs on 'time'"):
            sample(name, zero, SHAPE, 3, torch.Generator(), grid="logsnr")
    with pytest.raises(ValueError, match="grid 'karras' is not one of"):
        sample("ddim", zero, SHAPE, 3, torch.Generator(), grid="karras")
    with pytest.raises(ValueError, match="eta must be >= 0"):
        dpmpp_2m_sde_sample(zero, SHAPE, 3, torch.Generator(), eta=-0.5)


def test_dpmpp_2m_log_snr_grid_is_uniform_between_the_ends():
    seen = []

    def denoise(x_t, lam, cond):
        seen.append(lam[0].item())
        return torch.zeros_like(x_t)

    dpmpp_2m_sample(denoise, SHAPE, 4, torch.Generator().manual_seed(0), grid="logsnr")
    step = (LOG_SNR_MAX - LOG_SNR_MIN) / 4
    assert seen == pytest.approx([LOG_SNR_MIN + i * step for i in range(4)], abs=1e-5)


# --- DPM-Solver++(2M) SDE: stochastic, so its samples are compared as distributions ----------------------


@pytest.mark.parametrize("grid", ["time", "logsnr"])
def test_dpmpp_2m_sde_at_eta_zero_is_dpmpp_2m(grid):
    net = random_net()
    for denoise, shape in ((net, SHAPE), (gaussian_eps, TOY_SHAPE)):
        sde = dpmpp_2m_sde_sample(denoise, shape, 6, torch.Generator().manual_seed(4), eta=0.0, grid=grid)
        ode = dpmpp_2m_sample(denoise, shape, 6, torch.Generator().manual_seed(4), grid=grid)
        assert torch.equal(sde.x0, ode.x0)


def test_dpmpp_2m_sde_starts_as_ancestral_ddpm():
    """η = 1: the first update is the DDPM posterior step with the same noise, so two steps give DDPM's sample."""
    sde = dpmpp_2m_sde_sample(gaussian_eps, TOY_SHAPE, 2, torch.Generator().manual_seed(6), clip=False)
    ddpm = ddpm_sample(gaussian_eps, TOY_SHAPE, 2, torch.Generator().manual_seed(6), clip=False)
    torch.testing.assert_close(sde.x0, ddpm.x0, atol=1e-7, rtol=0)


def test_dpmpp_2m_sde_is_k_diffusion_step_in_its_coordinates():
    """k-diffusion `sample_dpmpp_2m_sde` (midpoint) on x/α with σ_k = σ/α = e^{−λ}, same noise: the same sample."""
    steps, eta = 7, 0.7
    lams = log_snr(torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64)).tolist()
    generator = torch.Generator().manual_seed(2)
    x = torch.randn(TOY_SHAPE, generator=generator).double() / math.sqrt(torch.sigmoid(torch.tensor(lams[0])))
    old = h_last = None
    for i in range(steps):
        alpha, sigma = (v.item() for v in alpha_sigma(torch.tensor(lams[i], dtype=torch.float64)))
        denoised = (alpha * x - sigma * gaussian_eps(alpha * x, torch.full((4,), lams[i]), None)) / alpha
        if i == steps - 1:
            break
        h = 0.5 * (lams[i + 1] - lams[i])  # −log σ_k(s) + log σ_k(t)
        x = math.exp(-h - eta * h) * x - math.expm1(-h - eta * h) * denoised
        if old is not None:
            x = x - 0.5 * math.expm1(-h - eta * h) * (h / h_last) * (denoised - old)
        x = x + math.exp(-0.5 * lams[i + 1]) * math.sqrt(-math.expm1(-2 * eta * h)) * torch.randn(
            TOY_SHAPE, generator=generator
        )
        old, h_last = denoised, h
    ours = dpmpp_2m_sde_sample(gaussian_eps, TOY_SHAPE, steps, torch.Generator().manual_seed(2), clip=False, eta=eta)
    torch.testing.assert_close(ours.x0, denoised, atol=1e-6, rtol=0)


def test_dpmpp_2m_sde_samples_the_data_distribution_better_than_ddpm():
    """x0 ~ N(0.3, 0.2²), 20k elements; measured (mean − μ, std − s), 1M elements: 2M SDE at 50 steps time grid
    (−0.0002, +0.0083), log-SNR grid (−0.0001, +0.0029); at 20 steps 2M SDE std −0.0093, DDPM −0.046."""
    shape = (4, 1, 1, 5000)
    for grid in ("time", "logsnr"):
        x0 = dpmpp_2m_sde_sample(gaussian_eps, shape, 50, torch.Generator().manual_seed(0), clip=False, grid=grid).x0
        assert abs(x0.mean().item() - MU) < 0.005, grid  # 3.5 standard errors of the mean of 20k
        assert abs(x0.std().item() - S) < 0.015, grid
    sde = dpmpp_2m_sde_sample(gaussian_eps, shape, 20, torch.Generator().manual_seed(0), clip=False).x0
    ddpm = ddpm_sample(gaussian_eps, shape, 20, torch.Generator().manual_seed(0), clip=False).x0
    assert abs(sde.std().item() - S) < abs(ddpm.std().item() - S) / 3


def test_mean_start_sets_x0_to_the_mean_below_the_threshold_only():
    """Per sample: x̂0 = (x_t − σ ε)/α equals the mean where log-SNR < below, the wrapped ε elsewhere; extra passes."""
    x_t = torch.randn(3, 2, 4, 5, generator=torch.Generator().manual_seed(0))
    lam = torch.tensor([-15.0, -11.0, -5.0])
    mean = torch.tensor([-0.5, 0.2]).view(2, 1, 1).expand(2, 4, 1)  # (C, H, 1), broadcast along the width
    wrapped = mean_start(lambda x, lam, cond: (torch.zeros_like(x), "mask"), mean, below=-10.0)
    eps, extra = wrapped(x_t, lam, None)
    alpha, sigma = alpha_sigma(lam.view(-1, 1, 1, 1))
    x0 = (x_t - sigma * eps) / alpha
    assert torch.allclose(x0[:2], mean.expand(2, 2, 4, 5), atol=1e-4) and extra == "mask"
    assert torch.equal(eps[2], torch.zeros_like(eps[2]))  # above the threshold: the network's own ε


LEVELS, SPREAD = (0.1, 0.5), 0.1  # two kinds of scan: every element of a sample ~ N(level, 0.1²), level 0.1 or 0.5


def mixture_eps(x_t: torch.Tensor, lam: torch.Tensor, cond: torch.Tensor | None) -> torch.Tensor:
    """Exact ε̂ of the two-level mixture: the posterior over each sample's level reads all its elements at once (as a
    net reads a scan's overall intensity), then E[x0 | x_t] per level as in `gaussian_eps`."""
    x_t = x_t.double()
    alpha, sigma = alpha_sigma(lam.double().view(-1, 1, 1, 1))
    var = alpha**2 * SPREAD**2 + sigma**2
    logp = torch.stack([-((x_t - alpha * m) ** 2).sum(dim=(1, 2, 3)) / (2 * var.view(-1)) for m in LEVELS], dim=1)
    weights = torch.softmax(logp, dim=1).view(-1, 2, 1, 1, 1)  # (B, 2, 1, 1, 1) posterior of each level
    x0 = sum(weights[:, k] * (m + alpha * SPREAD**2 * (x_t - alpha * m) / var) for k, m in enumerate(LEVELS))
    return (x_t - alpha * x0) / sigma


def test_mean_start_gives_back_what_an_exact_net_samples():
    """The exact mixture ε̂ except an error of 0.01 below log-SNR −10 (an ε-net's precision there): its x̂0 is off by
    0.01 σ/α (~18 at log-SNR −15, clamped) and some samples come out at the other level. At vanishing SNR the exact x̂0
    is the data mean, so with x̂0 = 0.3 there the samples are the exact net's (measured: max difference 1e-6 / 3e-5
    against 0.39 without)."""
    shape = (200, 1, 1, 64)

    def imprecise(x_t, lam, cond):
        return mixture_eps(x_t, lam, cond) - 0.01 * (lam.double() < -10).view(-1, 1, 1, 1)

    fixed = mean_start(imprecise, torch.tensor(sum(LEVELS) / 2, dtype=torch.float64), below=-10.0)
    for sampler in (dpmpp_2m_sde_sample, ddpm_sample):
        exact, off, started = (
            sampler(fn, shape, 20, torch.Generator().manual_seed(0)).x0 for fn in (mixture_eps, imprecise, fixed)
        )
        assert (off - exact).abs().max().item() > 0.2, sampler.__name__  # samples that switched level
        assert (started - exact).abs().max().item() < 1e-3, sampler.__name__


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_replace_known_keeps_the_known_pixels_and_conditions_the_rest(sampler):
    a = torch.linspace(-0.9, 0.9, 2 * 8 * 16).view(1, 2, 8, 16)  # the data are +a and -a, half each

    def generators() -> list[torch.Generator]:
        return [torch.Generator().manual_seed(i) for i in range(8)]

    free = sampler(two_point(a), (8, 2, 8, 16), 20, generators()).x0
    signs = torch.sign((free * a).sum(dim=(1, 2, 3)))
    assert (signs > 0).any() and (signs < 0).any()  # unconditioned: both modes are drawn
    mask = torch.zeros(1, 1, 8, 16)
    mask[..., :, :12] = 1.0  # three quarters of every image are known (about a warped frame's share): +a's pixels
    out = sampler(replace_known(two_point(a), a.expand(8, -1, -1, -1), mask), (8, 2, 8, 16), 20, generators()).x0
    torch.testing.assert_close(out[..., :12], a[..., :12].expand(8, -1, -1, -1))  # known pixels exactly as given
    torch.testing.assert_close(out[..., 12:], a[..., 12:].expand(8, -1, -1, -1), atol=1e-3, rtol=0)  # rest follows
    empty = replace_known(two_point(a), -a.expand(8, -1, -1, -1), torch.zeros(1))
    none = sampler(empty, (8, 2, 8, 16), 20, generators())
    torch.testing.assert_close(none.x0, free)  # an empty mask changes nothing
