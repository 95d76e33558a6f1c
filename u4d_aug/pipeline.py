"""Inference only (diffusers-pipeline style, no loss, no optimizer): U4D hard-to-easy generation, completion, baseline.

U4D (paper §2): x0_u ~ stage 1 with its mask head deciding which pixels are returns, then x0 ~ stage 2 given
concat(x0_u, m_u). Completion mode takes x0_u, m_u from real scans (so the frames keep those scans' poses).
The baseline is R2DM's single unconditional stage. Nets are loaded with their EMA weights.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.diffusion import stage_cond
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.nn.unet import RangeUNet
from u4d_aug.range_view import RowMode, unproject
from u4d_aug.sampling import Sample, ddim_sample, ddpm_sample
from u4d_aug.train import DiffusionTrainConfig, build_net, config_from_checkpoint, find_checkpoint

Sampler = Literal["ddim", "ddpm"]
Loaded = tuple[RangeUNet, DiffusionTrainConfig]


def load_generator(ckpt: str | Path, device: torch.device | str = "cpu") -> Loaded:
    """(net with the EMA weights, in eval mode; its training config) from a checkpoint file or a run folder."""
    path = Path(ckpt)
    if path.is_dir():
        path = find_checkpoint(path, "last")
    if not path.is_file():
        raise InputError(f"{path}: diffusion checkpoint not found")
    state = torch.load(path, map_location="cpu", weights_only=False)
    cfg = config_from_checkpoint(state, str(path))
    net = build_net(cfg, "cpu")
    ema = EMA(net)
    ema.load_state_dict(state["ema"])
    ema.copy_to(net)
    return net.requires_grad_(False).to(device).eval(), cfg


def _check_stage(loaded: Loaded, stage: str, role: str) -> None:
    if loaded[1].diffusion.stage != stage:
        raise InputError(f"{role}: expected a {stage} checkpoint, got {loaded[1].diffusion.stage}")


def _sample(
    loaded: Loaded, n: int, steps: int, generator: torch.Generator, cond: Tensor | None, sampler: Sampler
) -> Sample:
    net, cfg = loaded
    device = next(net.parameters()).device
    shape = (n, cfg.net.in_channels, cfg.height, cfg.width)
    if sampler == "ddim":
        return ddim_sample(net, shape, steps, generator, cond=cond, device=device)
    if sampler == "ddpm":
        return ddpm_sample(net, shape, steps, generator, cond=cond, device=device)
    raise InputError(f"sampler {sampler!r} is not one of 'ddim', 'ddpm'")


def generate_stage1(
    stage1: Loaded, n: int, steps: int, generator: torch.Generator, sampler: Sampler = "ddim"
) -> dict[str, Tensor]:
    """x0_u (n, 2, H, W) from stage 1: pixels whose mask logit gives sigmoid > 0.5 are returns, others −1."""
    _check_stage(stage1, "stage1", "stage 1")
    sample = _sample(stage1, n, steps, generator, None, sampler)
    m_u = (torch.sigmoid(sample.extra) > 0.5).float()  # (n, 1, H, W) predicted m_p of the last step
    x0_u = torch.where(m_u.bool(), sample.x0, torch.full_like(sample.x0, -1.0))
    return {"x0_u": x0_u, "m_u_pred": m_u}


def complete(
    stage2: Loaded,
    x0_u: Tensor,
    m_u: Tensor,
    steps: int,
    generator: torch.Generator,
    sampler: Sampler = "ddim",
) -> dict[str, Tensor]:
    """Stage 2: x0 (B, 2, H, W) ~ p(x0 | x0_u (B, 2, H, W), m_u (B, 1, H, W)), e.g. x0_u from real scans."""
    _check_stage(stage2, "stage2", "stage 2")
    net, cfg = stage2
    if x0_u.shape[-2:] != (cfg.height, cfg.width) or m_u.shape[-3:] != (1, cfg.height, cfg.width):
        raise InputError(
            f"stage 2 was trained on {cfg.height}x{cfg.width} images; "
            f"got x0_u {tuple(x0_u.shape)}, m_u {tuple(m_u.shape)}"
        )
    device = next(net.parameters()).device
    cond = stage_cond(x0_u.to(device), m_u.to(device))  # (B, 3, H, W)
    sample = _sample(stage2, x0_u.shape[0], steps, generator, cond, sampler)
    return {"x0": sample.x0, "x0_u": x0_u, "m_u": m_u}


def generate_u4d(
    stage1: Loaded,
    stage2: Loaded,
    n: int,
    steps: int,
    generator: torch.Generator,
    sampler: Sampler = "ddim",
    stage1_steps: int | None = None,
) -> dict[str, Tensor]:
    """Hard-to-easy: x0_u ~ stage 1 (mask from its head), then x0 ~ stage 2 given it -> dict(x0, x0_u, m_u_pred)."""
    if (stage1[1].height, stage1[1].width) != (stage2[1].height, stage2[1].width):
        raise InputError("stage 1 and stage 2 checkpoints were trained on different image sizes")
    first = generate_stage1(stage1, n, stage1_steps or steps, generator, sampler)
    second = complete(stage2, first["x0_u"], first["m_u_pred"], steps, generator, sampler)
    return {"x0": second["x0"], "x0_u": first["x0_u"], "m_u_pred": first["m_u_pred"]}


def generate_baseline(
    net: Loaded, n: int, steps: int, generator: torch.Generator, sampler: Sampler = "ddim"
) -> dict[str, Tensor]:
    """R2DM-style unconditional x0 (n, 2, H, W)."""
    _check_stage(net, "baseline", "baseline")
    return {"x0": _sample(net, n, steps, generator, None, sampler).x0}


def to_points(x0: Tensor, sensor: Sensor | str, row_mode: RowMode = "beam") -> list[np.ndarray]:
    """Range images (B, 2, H, W) -> B point clouds (M, 4) float32 [x, y, z, reflectance] of the valid pixels."""
    sensor = get_sensor(sensor) if not isinstance(sensor, Sensor) else sensor
    points, valid = unproject(x0.detach().float().cpu(), sensor, row_mode)  # (B, H, W, 4), (B, H, W)
    return [p[v].numpy().astype(np.float32) for p, v in zip(points, valid)]
