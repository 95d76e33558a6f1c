"""Samplers as free functions with one signature (k-diffusion style): they know the schedule, not the network.

`denoise_fn(x_t, log_snr, cond)` returns ε̂, or a tuple (ε̂, extra) whose `extra` (e.g. the stage-1 mask logits)
from the last network call is handed back with the sample. A `RangeUNet` is itself such a function.
Both samplers walk t = linspace(1, 0, steps + 1) on the cosine log-SNR of `u4d_aug.diffusion`, clamp
x̂0 = (x_t − σ ε̂)/α to [−1, 1] at every step and return the last x̂0 (R2DM
`ContinuousTimeGaussianDiffusion.sample`, generation_protocols.md §2.2).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor
from tqdm.auto import tqdm

from u4d_aug.diffusion import alpha_sigma, log_snr

DenoiseFn = Callable[[Tensor, Tensor, "Tensor | None"], "Tensor | tuple[Tensor, Any]"]
# one generator for the whole batch, or one per batch element: element i then draws exactly the noise a batch of
# one with generator i draws, so batching does not change what a seed generates
Generators = torch.Generator | Sequence[torch.Generator]


class Sample(NamedTuple):
    """Generated x0 (B, [L,] C, H, W) in [-1, 1] and the `extra` of the last denoiser call (or None)."""

    x0: Tensor
    extra: Any


@torch.no_grad()
def ddpm_sample(
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
) -> Sample:
    """Ancestral DDPM sampling in continuous time (Kingma et al. 2021, VDM; R2DM `sample`, mode ddpm)."""
    return _sample("ddpm", denoise_fn, shape, steps, generator, cond, device, progress)


@torch.no_grad()
def ddim_sample(
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None = None,
    device: torch.device | str | None = None,
    progress: bool = False,
) -> Sample:
    """Deterministic DDIM, η = 0 (Song et al. 2021, eq. 12); only x_1 ~ N(0, I) uses the generator."""
    return _sample("ddim", denoise_fn, shape, steps, generator, cond, device, progress)


def _sample(
    mode: Literal["ddpm", "ddim"],
    denoise_fn: DenoiseFn,
    shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None,
    device: torch.device | str | None,
    progress: bool,
) -> Sample:
    if steps < 1:
        raise ValueError(f"sampling steps must be >= 1, got {steps}")
    batch = shape[0]
    if not isinstance(generator, torch.Generator) and len(generator) != batch:
        raise ValueError(f"got {len(generator)} generators for a batch of {batch}")
    device = torch.device(device) if device is not None else _first(generator).device
    # the schedule in float64 python scalars: exact at the ends of the grid where alpha or sigma ~ 5e-4
    grid = log_snr(torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64)).tolist()
    x = _randn(shape, generator, device)  # x_1 ~ N(0, I)
    extra: Any = None
    for i in tqdm(range(steps), disable=not progress, desc=f"{mode} sampling", leave=False):
        lam_t, lam_s = grid[i], grid[i + 1]  # lam_s > lam_t: s is the less noisy time
        alpha_t, sigma_t = _alpha_sigma(lam_t)
        alpha_s, sigma_s = _alpha_sigma(lam_s)
        out = denoise_fn(x, torch.full((batch,), lam_t, device=device, dtype=torch.float32), cond)
        eps, extra = out if isinstance(out, tuple) else (out, None)
        x0_hat = ((x - sigma_t * eps) / alpha_t).clamp_(-1.0, 1.0)
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
