"""Samplers as free functions with one signature (k-diffusion style): they know the schedule, not the network.

`denoise_fn(x_t, log_snr, cond)` returns ε̂, or a tuple (ε̂, extra) whose `extra` (e.g. the stage-1 mask logits)
from the last network call is handed back with the sample. A `RangeUNet` is itself such a function.
All samplers make `steps` network calls on the cosine log-SNR of `u4d_aug.diffusion`, at the first `steps` points
of t = linspace(1, 0, steps + 1) (the DPM-Solver++ samplers can instead space them uniformly in log-SNR), clamp
x̂0 = (x_t − σ ε̂)/α to [−1, 1] at every step (`clip`) and return the last x̂0 (R2DM
`ContinuousTimeGaussianDiffusion.sample`, generation_protocols.md §2.2). `sample(name, ..., grid=)` picks one by
name. Only DDPM and DPM-Solver++(2M) SDE draw noise after x_1 (with the generators that drew x_1).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Literal, NamedTuple, get_args

import torch
from torch import Tensor

from u4d_aug.diffusion import alpha_sigma, log_snr
from u4d_aug.errors import InputError
from u4d_aug.memory import check_fits
from u4d_aug.progress import progress_bar

DenoiseFn = Callable[[Tensor, Tensor, "Tensor | None"], "Tensor | tuple[Tensor, Any]"]
# one generator for the whole batch, or one per batch element: element i then draws exactly the noise a batch of
# one with generator i draws, so batching does not change what a seed generates
Generators = torch.Generator | Sequence[torch.Generator]


class Sample(NamedTuple):
    """Generated x0 (B, [L,] C, H, W) in [-1, 1] and the `extra` of the last denoiser call (or None)."""

    x0: Tensor
    extra: Any


SamplerName = Literal["ddpm", "ddim", "dpmpp2m", "dpmpp2m-sde"]
SAMPLER_NAMES: tuple[str, ...] = get_args(SamplerName)
Grid = Literal["time", "logsnr"]
GRID_NAMES: tuple[str, ...] = get_args(Grid)
GRID_SAMPLERS: tuple[str, ...] = ("dpmpp2m", "dpmpp2m-sde")  # the samplers that also run on the "logsnr" grid


def mean_start(denoise_fn: DenoiseFn, mean: Tensor, below: float) -> DenoiseFn:
    """`denoise_fn` whose x̂0 is `mean` (broadcast to each sample, e.g. a (C, H, 1) per-row mean image) for the
    samples with log-SNR < `below`, and unchanged above.

    At vanishing SNR the MMSE estimate of x0 is the data mean, while an ε-network's x̂0 = (x_t − σ ε̂)/α divides its
    error by α (5e-4 at log-SNR −15): clamped noise that the samplers' first steps keep
    (benchmarks/results/generation/mean_start_diagnostic.md). There the returned ε is (x_t − α μ)/σ, the ε of x̂0 = μ;
    the `extra` of the wrapped function (stage-1 mask logits) is passed through.
    """

    def wrapped(x_t: Tensor, lam: Tensor, cond: Tensor | None) -> Tensor | tuple[Tensor, Any]:
        out = denoise_fn(x_t, lam, cond)
        eps, extra = out if isinstance(out, tuple) else (out, None)
        lam_b = lam.reshape(-1)  # (B,), or (1,) for a log-SNR shared by the batch
        low = lam_b < below
        if bool(low.any()):
            alpha, sigma = alpha_sigma(lam_b.view(-1, *([1] * (x_t.dim() - 1))))
            eps_mean = (x_t - alpha * mean.to(x_t.device, x_t.dtype)) / sigma
            eps = torch.where(low.view(-1, *([1] * (x_t.dim() - 1))), eps_mean.to(eps.dtype), eps)
        return (eps, extra) if isinstance(out, tuple) else eps

    return wrapped


def replace_known(denoise_fn: DenoiseFn, x0_known: Tensor, mask: Tensor) -> DenoiseFn:
    """`denoise_fn` whose x̂0 is `x0_known` where `mask` ({0, 1}, broadcast to x_t) is 1: inpainting an
    unconditional net by replacement (Song et al. 2021, score SDE app. I; RePaint without resampling).

    The returned ε is (x_t − α x̂0')/σ of the replaced x̂0', so every sampler's next x_s carries the known pixels
    noised to its level and the last x̂0 is `x0_known` there; the `extra` of the wrapped function is passed through.
    """

    def wrapped(x_t: Tensor, lam: Tensor, cond: Tensor | None) -> Tensor | tuple[Tensor, Any]:
        out = denoise_fn(x_t, lam, cond)
        eps, extra = out if isinstance(out, tuple) else (out, None)
        alpha, sigma = alpha_sigma(lam.reshape(-1).view(-1, *([1] * (x_t.dim() - 1))).to(x_t.dtype))
        eps_known = (x_t - alpha * x0_known.to(x_t.device, x_t.dtype)) / sigma  # the ε of x̂0 = x0_known
        eps = torch.where(mask.to(x_t.device).bool().expand_as(x_t), eps_known.to(eps.dtype), eps)  # others exact
        return (eps, extra) if isinstance(out, tuple) else eps

    return wrapped


def sample(
    name: SamplerName,
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
    clip: bool = True,
    grid: Grid = "time",
) -> Sample:
    """The sampler called `name`: ddpm | ddim | dpmpp2m | dpmpp2m-sde (η = 1), on `grid` (see `check_grid`)."""
    check_grid(name, grid)
    if name == "ddpm":
        return ddpm_sample(denoise_fn, shape, steps, generator, cond, device, progress, clip)
    elif name == "ddim":
        return ddim_sample(denoise_fn, shape, steps, generator, cond, device, progress, clip)
    elif name == "dpmpp2m":
        return dpmpp_2m_sample(denoise_fn, shape, steps, generator, cond, device, progress, clip, grid=grid)
    elif name == "dpmpp2m-sde":
        return dpmpp_2m_sde_sample(denoise_fn, shape, steps, generator, cond, device, progress, clip, grid=grid)
    raise ValueError(f"sampler {name!r} is not one of {', '.join(repr(n) for n in SAMPLER_NAMES)}")


def check_grid(name: str, grid: str) -> None:
    """ValueError unless `grid` is "time" or "logsnr" and sampler `name` runs on it (ddpm, ddim: "time" only)."""
    if grid not in GRID_NAMES:
        raise ValueError(f"grid {grid!r} is not one of {', '.join(repr(g) for g in GRID_NAMES)}")
    if grid != "time" and name not in GRID_SAMPLERS:
        accepting = ", ".join(repr(n) for n in GRID_SAMPLERS)
        raise ValueError(f"grid {grid!r} is accepted only by the samplers {accepting}; {name!r} runs on 'time'")


@torch.no_grad()
def ddpm_sample(
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
    clip: bool = True,
) -> Sample:
    """Ancestral DDPM sampling in continuous time (Kingma et al. 2021, VDM; R2DM `sample`, mode ddpm)."""
    return _sample("ddpm", denoise_fn, shape, steps, generator, cond, device, progress, clip)


@torch.no_grad()
def ddim_sample(
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
    clip: bool = True,
) -> Sample:
    """Deterministic DDIM, η = 0 (Song et al. 2021, eq. 12); only x_1 ~ N(0, I) uses the generator."""
    return _sample("ddim", denoise_fn, shape, steps, generator, cond, device, progress, clip)


@torch.no_grad()
def dpmpp_2m_sample(
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
    clip: bool = True,
    grid: Grid = "time",
) -> Sample:
    """DPM-Solver++(2M), multistep 2nd order in x̂0 on λ = log(α/σ) (Lu et al. 2022, Alg. 2; k-diffusion).

    The first step is first order (= DDIM); the last call's x̂0 is returned, as by the other samplers (a step
    to σ = 0, first order as in k-diffusion `sample_dpmpp_2m`), so `steps` = 1 is DDIM with one step. `grid`:
    "time" = the other samplers' t = linspace(1, 0, steps + 1), "logsnr" = uniform in log-SNR between its ends.
    Only x_1 ~ N(0, I) uses the generator.
    """
    lams = log_snr_grid(steps, grid)  # log-SNR = 2λ at the steps + 1 grid points, rising
    batch, device, x = _start(shape, steps, generator, device)
    extra: Any = None
    x0_prev: Tensor | None = None  # x̂0 of the previous call, the second point of the multistep
    for i in progress_bar(range(steps), enabled=progress, desc="dpmpp2m sampling", leave=False):
        eps, extra = _denoise(denoise_fn, x, lams[i], batch, device, cond)
        alpha_t, sigma_t = _alpha_sigma(lams[i])
        x0_hat = (x - sigma_t * eps) / alpha_t
        if clip:
            x0_hat.clamp_(-1.0, 1.0)
        if i == steps - 1:
            x = x0_hat
            break
        alpha_s, sigma_s = _alpha_sigma(lams[i + 1])
        h = 0.5 * (lams[i + 1] - lams[i])  # h_i = λ_s − λ_t > 0 in DPM-Solver's half log-SNR
        d = x0_hat
        if x0_prev is not None:
            r = 0.5 * (lams[i] - lams[i - 1]) / h  # r_i = h_{i−1} / h_i
            d = (1.0 + 0.5 / r) * x0_hat - (0.5 / r) * x0_prev  # D_i, the 2nd-order x̂0 over [λ_t, λ_s]
        x = (sigma_s / sigma_t) * x - alpha_s * math.expm1(-h) * d  # x_s = σ_s/σ_t x_t − α_s (e^{−h} − 1) D_i
        x0_prev = x0_hat
    return Sample(x, extra)


@torch.no_grad()
def dpmpp_2m_sde_sample(
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
    clip: bool = True,
    eta: float = 1.0,
    grid: Grid = "time",
) -> Sample:
    """DPM-Solver++(2M) SDE, midpoint form, in x̂0 on λ = log(α/σ) (Lu et al. 2022; k-diffusion `sample_dpmpp_2m_sde`).

    Update from the noisier t to s (h = λ_s − λ_t > 0; VP x_t = α_t x0 + σ_t ε, so σ_s α_t / σ_t = α_s e^{−h}):
    keep the share e^{−ηh} of the noise direction ε̂ = (x_t − α_t x̂0)/σ_t and replace the rest by fresh noise z,
        x_s = α_s x̂0 + σ_s (e^{−ηh} ε̂ + sqrt(1 − e^{−2ηh}) z)
            = σ_s/σ_t e^{−ηh} x_t + α_s (1 − e^{−(1+η)h}) x̂0 + σ_s sqrt(1 − e^{−2ηh}) z,
    which keeps x_s ~ N(α_s x0, σ_s²) when x̂0 = x0 (k-diffusion's σ is our σ/α, its x our x/α: the same step).
    2M puts D = (1 + 1/(2r)) x̂0 − 1/(2r) x̂0_prev, r = h_prev / h, in place of x̂0 from the second step on.
    η = 0 is `dpmpp_2m_sample` and draws no noise; with η = 1 the first step is ancestral DDPM's, the posterior
    q(x_s | x_t, x̂0). z is drawn at every step but the last, like `ddpm_sample` (independent per step, not
    k-diffusion's Brownian tree); the last call's x̂0 is returned. `grid` as in `dpmpp_2m_sample`.
    """
    if eta < 0:
        raise ValueError(f"eta must be >= 0, got {eta}")
    lams = log_snr_grid(steps, grid)  # log-SNR = 2λ at the steps + 1 grid points, rising
    batch, device, x = _start(shape, steps, generator, device)
    extra: Any = None
    x0_prev: Tensor | None = None
    for i in progress_bar(range(steps), enabled=progress, desc="dpmpp2m-sde sampling", leave=False):
        eps, extra = _denoise(denoise_fn, x, lams[i], batch, device, cond)
        alpha_t, sigma_t = _alpha_sigma(lams[i])
        x0_hat = (x - sigma_t * eps) / alpha_t
        if clip:
            x0_hat.clamp_(-1.0, 1.0)
        if i == steps - 1:
            x = x0_hat
            break
        alpha_s, sigma_s = _alpha_sigma(lams[i + 1])
        h = 0.5 * (lams[i + 1] - lams[i])
        d = x0_hat
        if x0_prev is not None:
            r = 0.5 * (lams[i] - lams[i - 1]) / h
            d = (1.0 + 0.5 / r) * x0_hat - (0.5 / r) * x0_prev
        # x_s = σ_s/σ_t e^{−ηh} x_t − α_s (e^{−(1+η)h} − 1) D [+ σ_s sqrt(1 − e^{−2ηh}) z]
        x = (sigma_s / sigma_t * math.exp(-eta * h)) * x - alpha_s * math.expm1(-(1.0 + eta) * h) * d
        if eta > 0:
            x = x + sigma_s * math.sqrt(-math.expm1(-2.0 * eta * h)) * _randn(shape, generator, device)
        x0_prev = x0_hat
    return Sample(x, extra)


def _sample(
    mode: Literal["ddpm", "ddim"],
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None,
    device: torch.device | str | None,
    progress: bool,
    clip: bool,
) -> Sample:
    batch, device, x = _start(shape, steps, generator, device)
    grid = log_snr_grid(steps, "time")
    extra: Any = None
    for i in progress_bar(range(steps), enabled=progress, desc=f"{mode} sampling", leave=False):
        lam_t, lam_s = grid[i], grid[i + 1]  # lam_s > lam_t: s is the less noisy time
        alpha_t, sigma_t = _alpha_sigma(lam_t)
        alpha_s, sigma_s = _alpha_sigma(lam_s)
        eps, extra = _denoise(denoise_fn, x, lam_t, batch, device, cond)
        x0_hat = (x - sigma_t * eps) / alpha_t
        if clip:
            x0_hat.clamp_(-1.0, 1.0)
        if i == steps - 1:
            x = x0_hat
        elif mode == "ddpm":
            c = -math.expm1(lam_t - lam_s)  # 1 - SNR(t)/SNR(s)
            mean = alpha_s * ((1.0 - c) / alpha_t * x + c * x0_hat)
            x = mean + sigma_s * math.sqrt(c) * _randn(shape, generator, device)
        else:
            eps = (x - alpha_t * x0_hat) / sigma_t  # re-derived from the clamped x̂0 so both stay consistent
            x = alpha_s * x0_hat + sigma_s * eps
    return Sample(x, extra)


GRID_BYTES_PER_STEP = 64  # a step's grid values as float64 tensors and python floats


def _start(
    shape: tuple[int, ...], steps: int, generator: Generators, device: torch.device | str | None
) -> tuple[int, torch.device, Tensor]:
    """(batch B, device, x_1 ~ N(0, I) of `shape`) after checking steps >= 1 and one generator per element."""
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise InputError(f"steps: sampling steps must be an integer >= 1, got {steps!r}")
    check_fits(GRID_BYTES_PER_STEP * steps, f"steps={steps} (the sampler's log-SNR grid)", "lower steps")
    batch = shape[0]
    if not isinstance(batch, int) or batch < 1:
        raise InputError(f"n: the number of samples must be an integer >= 1, got {batch!r}")
    if isinstance(generator, (str, bytes)) or not (
        isinstance(generator, torch.Generator)
        or (isinstance(generator, Sequence) and all(isinstance(g, torch.Generator) for g in generator))
    ):
        raise InputError(f"generator: expected a torch.Generator or one per sample, got {type(generator).__name__}")
    if not isinstance(generator, torch.Generator) and len(generator) != batch:
        raise InputError(f"generator: got {len(generator)} generators for a batch of {batch} (one per sample)")
    device = torch.device(device) if device is not None else _first(generator).device
    return batch, device, _randn(shape, generator, device)


def log_snr_grid(steps: int, kind: Grid) -> list[float]:
    """log-SNR at steps + 1 points from t = 1 to t = 0, uniform in t or in log-SNR (float64: exact at the ends)."""
    if kind == "time":
        return log_snr(torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64)).tolist()
    if kind == "logsnr":
        lo, hi = log_snr(torch.tensor([1.0, 0.0], dtype=torch.float64)).tolist()
        return torch.linspace(lo, hi, steps + 1, dtype=torch.float64).tolist()
    raise ValueError(f"grid {kind!r} is not one of 'time', 'logsnr'")


def _denoise(
    denoise_fn: DenoiseFn, x: Tensor, lam: float, batch: int, device: torch.device, cond: Tensor | None
) -> tuple[Tensor, Any]:
    """(ε̂ of x_t at log-SNR `lam`, given to the net as (B,) float32; the call's extra or None)."""
    out = denoise_fn(x, torch.full((batch,), lam, device=device, dtype=torch.float32), cond)
    return out if isinstance(out, tuple) else (out, None)


def _alpha_sigma(lam: float) -> tuple[float, float]:
    alpha, sigma = alpha_sigma(torch.tensor(lam, dtype=torch.float64))
    return float(alpha), float(sigma)


def _first(generator: Generators) -> torch.Generator:
    return generator if isinstance(generator, torch.Generator) else generator[0]


def _randn(shape: tuple[int, ...], generator: Generators, device: torch.device) -> Tensor:
    """Noise drawn on the generator's device, then moved: a CPU generator gives one sample on any device.

    With one generator per batch element, element i is drawn alone from generator i, shape (1, *shape[1:]).
    """
    if isinstance(generator, torch.Generator):
        return torch.randn(shape, generator=generator, device=generator.device).to(device)
    parts = [torch.randn((1, *shape[1:]), generator=g, device=g.device).to(device) for g in generator]
    return torch.cat(parts)
