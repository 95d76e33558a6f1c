"""Inference only (diffusers-pipeline style, no loss, no optimizer): U4D hard-to-easy generation, completion, baseline.

U4D (paper §2): x0_u ~ stage 1 with its mask head deciding which pixels are returns, then x0 ~ stage 2 given
concat(x0_u, m_u). Completion mode takes x0_u, m_u from real scans (so the frames keep those scans' poses).
The baseline is R2DM's single unconditional stage. A cascade's detail net (`refine`) completes the full-width scan
from the columns a layout net (either method's) generated at W / s. Nets are loaded with their EMA weights.
A net trained with `frames` = L > 1 generates L-frame sequences at once: tensors (n, L, C, H, W) instead of
(n, C, H, W) (its MoST blocks, if any, mix the frames). `frames=` asks for another length: the temporal convs
slide along L, so any L works, and a single-frame net then makes L independent frames.
Every sampling function reads one `SamplingSettings` (sampler, steps, stage-1 options, mean start), the settings
`u4d generate` builds from its config, so the API makes the scans the CLI makes.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from u4d_aug.batches import row_mean_key
from u4d_aug.cascade import place_columns
from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.diffusion import STAGE1_TASK, STAGE2_TASK, empty_condition, eps_from_v, stage_cond
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.io import load_checkpoint
from u4d_aug.latent import (
    LatentNet,
    autoencoder_of,
    from_latent,
    latent_mask,
    load_latent_autoencoder,
    pixel_mask,
    to_latent,
)
from u4d_aug.propagate import warp_frame0
from u4d_aug.range_view import RowMode, unproject
from u4d_aug.run import newest_checkpoint
from u4d_aug.sampling import DenoiseFn, Generators, Sample, mean_start, replace_known
from u4d_aug.sampling import sample as sample_named
from u4d_aug.sampling_settings import DEFAULT_SAMPLING, SamplingSettings
from u4d_aug.stage import DiffusionTrainConfig, build_net, config_from_checkpoint
from u4d_aug.validate import check_state_fits
from u4d_aug.weights import check_finite_weight, is_exported, load_exported, stored_row_mean

# u4d_aug.sampling.sample: DDIM, ancestral DDPM, DPM-Solver++(2M) and its SDE form; the last two also on grid="logsnr"
Sampler = Literal["ddim", "ddpm", "dpmpp2m", "dpmpp2m-sde"]
# what the samplers take: a `LoadedGenerator`, or any (net, config) pair such as (MeanStart(net, ...), config)
Loaded = tuple[nn.Module, DiffusionTrainConfig]


class LoadedGenerator(NamedTuple):
    """A diffusion net with its EMA weights, in eval mode, and its training config (`load_generator`); unpacks as
    `net, config = ...`. A net from exported weights also holds the training means they store (`stored_mean`) as
    buffers `row_mean_<role>`, which the mean start (`SamplingSettings.mean_start_below`) starts from."""

    net: nn.Module  # a RangeUNet, or a LatentNet (the net and its autoencoder) for a latent generator
    config: DiffusionTrainConfig


def load_generator(ckpt: str | Path, device: torch.device | str = "cpu") -> LoadedGenerator:
    """LoadedGenerator(net with the EMA weights, in eval mode; its training config) from a checkpoint, exported
    weights (`u4d_aug.weights`) or a run folder."""
    path = Path(ckpt)
    if path.is_dir():
        path = newest_checkpoint(path)
    state = load_checkpoint(path, "diffusion checkpoint")
    cfg = config_from_checkpoint(state, str(path))
    net = build_net(cfg, "cpu")
    if is_exported(state):  # `u4d export-weights`: the EMA weights in float16
        load_exported(net, state, str(path))
        for role in _roles(cfg):
            stored = stored_mean(state, cfg, role, str(path))
            if stored is not None:  # non-persistent: the net's state_dict stays that of its config
                net.register_buffer(f"row_mean_{role}", stored[0], persistent=False)
    else:
        shadow = state.get("ema")
        if not isinstance(shadow, dict):
            raise InputError(
                f"{path}: no EMA weights ('ema'); expected a train-diffusion checkpoint or exported weights"
            )
        check_state_fits(shadow.get("params"), dict(net.named_parameters()), f"{path} (ema)")
        check_state_fits(shadow.get("buffers"), dict(net.named_buffers()), f"{path} (ema buffers)")
        ema = EMA(net)
        ema.load_state_dict(shadow)
        ema.copy_to(net)
        for name, tensor in net.state_dict().items():  # a diverged run's EMA would sample NaN scans
            if tensor.is_floating_point():
                check_finite_weight(tensor, name, f"{path} (ema)")
    loaded: nn.Module = net
    if cfg.autoencoder:  # a latent generator samples latents and decodes them with its autoencoder
        loaded = LatentNet(net, load_latent_autoencoder(cfg, "cpu", base=path.parent))
    return LoadedGenerator(loaded.requires_grad_(False).to(device).eval(), cfg)


def _roles(cfg: DiffusionTrainConfig) -> tuple[str, ...]:
    """The roles a net of `cfg` samples in: its stage, or stage 1 and stage 2 for a one-net u4d."""
    return ("stage1", "stage2") if cfg.diffusion.stage == "u4d" else (cfg.diffusion.stage,)


def stored_mean(state: dict, cfg: DiffusionTrainConfig, role: str, source: str) -> tuple[Tensor, dict] | None:
    """(C, H, 1) per-row training mean that exported weights store for a net's `role` (`weights.stored_row_mean`)
    and where it came from, or None without one; an InputError when it is the mean of other images or rows."""
    if cfg.diffusion.stage == "u4d" and role == "stage1" and "row_mean_stage1" not in state:
        return None  # a one-net file's `row_mean` is its x0 mean; its stage-1 mean could not be read at export
    stored = stored_row_mean(state, source, role)
    if stored is None:
        return None
    mean, info = stored
    key = row_mean_key(cfg, role)
    rows = cfg.height // (cfg.latent_factor or 1)  # a latent generator's is the mean of its latents
    if info.get("key") != key or mean.shape[1] != rows or bool(cfg.latent_factor) != bool(info.get("latent")):
        what = "latent " if cfg.latent_factor else ""
        raise InputError(
            f"{source}: row_mean: expected the {key} {what}mean of {rows} rows, got {info.get('key')} "
            f"of shape {tuple(mean.shape)}{' (latent)' if info.get('latent') else ''}"
        )
    return mean, info


class MeanStart(nn.Module):
    """A loaded net whose x̂0 is `mean` (C, H, 1) below log-SNR `below` (`sampling.mean_start`): the samplers' first
    steps start from the training scans' mean instead of an ε-net's x̂0 at α ≈ 0 (clamped noise)."""

    mean: Tensor  # a buffer (C, H, 1)

    def __init__(self, net: nn.Module, mean: Tensor, below: float) -> None:
        super().__init__()
        self.net = net
        self.register_buffer("mean", mean.float())
        self.below = float(below)

    def forward(
        self, x_t: Tensor, log_snr: Tensor, cond: Tensor | None = None, **kwargs
    ) -> Tensor | tuple[Tensor, Any]:
        def denoise(x: Tensor, lam: Tensor, c: Tensor | None) -> tuple[Tensor, Tensor | None]:
            return self.net(x, lam, c, **kwargs)

        return mean_start(denoise, self.mean, self.below)(x_t, log_snr, cond)


def with_mean_start(loaded: Loaded, role: str, settings: SamplingSettings) -> Loaded:
    """`loaded` in a `MeanStart` of the training mean its weights file stores for `role` (the net's buffer
    `row_mean_<role>`, `load_generator`) when settings.mean_start_below is set; as it is when that is None or its
    net is already in a MeanStart; a latent generator without a stored mean starts from the zero latent (its
    latents are normalised to zero mean per channel); an InputError naming the way out for another net without one."""
    if not isinstance(settings, SamplingSettings):
        raise InputError(
            f"settings: expected a SamplingSettings (sampler, steps, ...: u4d_aug.SamplingSettings(steps=8)), "
            f"got {type(settings).__name__}"
        )
    net, cfg = loaded
    below = settings.mean_start_below
    if below is None or isinstance(net, MeanStart):
        return loaded
    holder = net.net if isinstance(net, LatentNet) else net  # the stored means are buffers of the diffusion net
    mean = dict(holder.named_buffers(recurse=False)).get(f"row_mean_{role}")
    if mean is None and autoencoder_of(net) is not None:  # the latents are normalised to zero mean per channel
        mean = torch.zeros(cfg.net.in_channels, cfg.height // cfg.latent_factor, 1)
    if mean is None:
        raise InputError(
            f"mean_start_below={below}: this {cfg.diffusion.stage} net has no stored training mean for {role} (only "
            "weights written by `u4d export-weights --data-root` hold one); export it that way or set "
            "mean_start_below=None"
        )
    return MeanStart(net, mean, below), cfg


def _check_stage(loaded: Loaded, stage: str, role: str) -> None:
    """A net for `role`: a checkpoint of that stage, or a u4d net (both stages in one) for stage 1 or stage 2."""
    _, cfg = loaded
    got = cfg.diffusion.stage
    if got != stage and not (got == "u4d" and stage in ("stage1", "stage2")):
        raise InputError(f"{role}: expected a {stage} (or one-net u4d) checkpoint, got {got}")


def _batch_shape(n: int, frames: int) -> tuple[int, ...]:
    """(n,) for single scans, (n, L) for L-frame sequences."""
    return (n,) if frames == 1 else (n, frames)


def denoiser(
    loaded: Loaded, batch_shape: tuple[int, ...], motion: Tensor | None = None, task: int | None = None
) -> DenoiseFn:
    """The ε̂ function a sampler calls for a loaded net, built from the inside out: the net with its per-sample
    inputs (ego motion (*batch_shape, P), `task` of a u4d net: STAGE1_TASK runs with the empty condition), ε̂ from a
    v-prediction, the mean start of a `MeanStart` net."""
    net, cfg = loaded
    device = next(net.parameters()).device
    inner, start = (net.net, net) if isinstance(net, MeanStart) else (net, None)
    inputs: dict = {}
    if cfg.net.pose_dim:  # the net reads each frame's ego motion: bind it into the sampler's denoise function
        if motion is None or tuple(motion.shape) != (*batch_shape, cfg.net.pose_dim):
            got = None if motion is None else tuple(motion.shape)
            raise InputError(
                f"this {cfg.diffusion.stage} net is conditioned on ego motion: expected motion {(*batch_shape, 4)} "
                f"(x, y, z, yaw per frame, u4d_aug.trajectory), got {got}"
            )
        inputs["poses"] = motion.to(device, torch.float32)
    elif motion is not None:
        raise InputError(f"this {cfg.diffusion.stage} net has no ego-motion input (net.pose_dim = 0); drop motion")
    if cfg.diffusion.stage == "u4d":
        if task not in (STAGE1_TASK, STAGE2_TASK):
            raise InputError(
                f"a u4d net samples stage 1 (task {STAGE1_TASK}) or stage 2 (task {STAGE2_TASK}), got {task}"
            )
        inputs["task"] = task
    denoise: DenoiseFn = functools.partial(_with_inputs, inner, inputs) if inputs else inner
    if cfg.diffusion.parameterization == "v":
        denoise = functools.partial(_eps_of_v, denoise)
    if start is not None:
        denoise = mean_start(denoise, start.mean, start.below)
    return denoise


def _sample(
    loaded: Loaded,
    batch_shape: tuple[int, ...],
    steps: int,
    generator: Generators,
    cond: Tensor | None,
    settings: SamplingSettings,
    motion: Tensor | None = None,
    known: tuple[Tensor, Tensor] | None = None,
    task: int | None = None,
) -> Sample:
    """The settings' sampler and grid at `steps` on the loaded net (`denoiser`); `known` (x0 (*batch, C, H, W), mask
    (*batch, 1, H, W)) pins x̂0 where mask is 1 (`replace_known`); `task`: which stage a u4d net runs."""
    net, cfg = loaded
    device = next(net.parameters()).device
    factor = cfg.latent_factor or 1  # a latent generator samples its autoencoder's latent
    shape = (*batch_shape, cfg.net.in_channels, cfg.height // factor, cfg.width // factor)
    denoise = denoiser(loaded, batch_shape, motion, task)
    if known is not None:
        denoise = replace_known(denoise, known[0].to(device), known[1].to(device))
    clip = autoencoder_of(net) is None  # x̂0 of a range image lies in [-1, 1]; a latent's is unbounded
    return sample_named(
        settings.sampler, denoise, shape, steps, generator, cond=cond, device=device, grid=settings.grid, clip=clip
    )


def _with_inputs(net: nn.Module, inputs: dict, x_t: Tensor, log_snr: Tensor, cond: Tensor | None):
    """The denoise function of a net with per-sample inputs (`poses`, `task`): ε̂, mask logits of (x_t, log-SNR,
    cond); a u4d net's stage-1 task gets the empty condition."""
    if inputs.get("task") == STAGE1_TASK and cond is None:
        cond = empty_condition(x_t)
    return net(x_t, log_snr, cond, **inputs)


def _eps_of_v(denoise, x_t: Tensor, log_snr: Tensor, cond: Tensor | None):
    """ε̂ (and the extra output) of a v-predicting denoise function (`diffusion.eps_from_v`)."""
    out = denoise(x_t, log_snr, cond)
    v, extra = out if isinstance(out, tuple) else (out, None)
    eps = eps_from_v(x_t, torch.as_tensor(log_snr, device=x_t.device).expand(x_t.shape[0]), v)
    return (eps, extra) if isinstance(out, tuple) else eps


def mask_from_logits(logits: Tensor, pos_weight: float = 1.0) -> Tensor:
    """m_p {0, 1} where the calibrated probability of an uncertain return exceeds 1/2.

    A head trained with BCE whose positives weigh `pos_weight` = w converges to logit = log(w·q / (1 − q)) for a
    pixel that is uncertain with probability q, so q > 1/2 is logit > log w (plain sigmoid > 0.5 would keep
    pixels down to q = 1/(1 + w) and inflate the mask; measured on the CPU stage 1 with w = 4: 42% of pixels
    against 17% in real P_u).
    """
    return (logits > math.log(pos_weight)).float()


def cap_mask(m_u: Tensor, logits: Tensor, fraction: float) -> Tensor:
    """m_u (..., 1, H, W) cut to at most `fraction` of each frame's pixels, those of the highest mask logits.

    P_u is the top-K entropy set of a fixed size (paper §2), so its range-view mask covers a nearly fixed share of
    the pixels (10.3 % of a 64x1024 HDL-64E image for K = 10 % of the points); a stage-1 head that keeps too many
    pixels is cut back to that size. Ties at the K-th logit are all kept.
    """
    flat = logits.flatten(-3)  # (..., H·W) one frame per row
    k = max(1, int(round(fraction * flat.shape[-1])))
    kth = flat.topk(k, dim=-1).values[..., -1:]  # (..., 1) the K-th largest logit
    return m_u * (flat >= kth).float().view_as(m_u)


def generate_stage1(
    stage1: Loaded,
    n: int,
    generator: Generators,
    settings: SamplingSettings = DEFAULT_SAMPLING,
    frames: int | None = None,
    motion: Tensor | None = None,
) -> dict[str, Tensor]:
    """x0_u (n, [L,] 2, H, W) from stage 1: pixels of the predicted mask m_p (`mask_from_logits`) keep x̂0, others −1.

    Sampled at settings.stage1_steps (None: steps), from the stored mean with settings.mean_start_below
    (`with_mean_start`); m_p keeps at most settings.stage1_mask_fraction of each frame's pixels (`cap_mask`; None:
    the threshold alone). `frames` = L (None: the L stage 1 was trained with; a single-frame net makes L independent
    frames). `motion` (n, L, 4): the ego motion of each frame, for nets trained with it (net.pose_dim).
    """
    _check_stage(stage1, "stage1", "stage 1")
    stage1 = with_mean_start(stage1, "stage1", settings)
    _, cfg = stage1
    shape = _batch_shape(n, frames or cfg.frames)
    steps = settings.stage1_steps or settings.steps
    sample = _sample(stage1, shape, steps, generator, None, settings, motion, task=STAGE1_TASK)
    x0, logits = sample.x0, sample.extra
    autoencoder = autoencoder_of(stage1[0])
    if autoencoder is not None:  # a latent stage 1: its image decoded, its mask head's logits on the f x f pixels
        x0, logits = from_latent(autoencoder, x0), pixel_mask(logits, cfg.latent_factor)
    m_u = mask_from_logits(logits, cfg.diffusion.mask_pos_weight)  # (n, [L,] 1, H, W), last step
    if autoencoder is not None:  # P_u is a set of points: the mask keeps the decoded returns only
        m_u = m_u * (x0[..., :1, :, :] > -1.0).to(m_u.dtype)
    if settings.stage1_mask_fraction is not None:
        m_u = cap_mask(m_u, logits, settings.stage1_mask_fraction)
    x0_u = torch.where(m_u.bool(), x0, torch.full_like(x0, -1.0))
    return {"x0_u": x0_u, "m_u_pred": m_u}


def complete(
    stage2: Loaded,
    x0_u: Tensor,
    m_u: Tensor,
    generator: Generators,
    settings: SamplingSettings = DEFAULT_SAMPLING,
    motion: Tensor | None = None,
    pin_known: bool = False,
) -> dict[str, Tensor]:
    """Stage 2: x0 (B, [L,] 2, H, W) ~ p(x0 | x0_u (B, [L,] 2, H, W), m_u (B, [L,] 1, H, W)), e.g. from real scans.

    Sampled at settings.steps, from the stored mean with settings.mean_start_below (`with_mean_start`). `motion`
    (B, L, 4): the ego motion of each frame, for nets trained with it (net.pose_dim). `pin_known`: x̂0 is also pinned
    to x0_u where m_u is 1 at every step (`replace_known`, as the baseline's `inpaint`)."""
    _check_stage(stage2, "stage2", "stage 2")
    stage2 = with_mean_start(stage2, "stage2", settings)
    net, cfg = stage2
    if (
        x0_u.dim() not in (4, 5)
        or x0_u.shape[-3:] != (2, cfg.height, cfg.width)
        or m_u.shape != (*x0_u.shape[:-3], 1, cfg.height, cfg.width)
    ):
        raise InputError(
            f"stage 2 was trained on {cfg.height}x{cfg.width} images: expected x0_u (B, [L,] 2, H, W) and m_u "
            f"(B, [L,] 1, H, W), got x0_u {tuple(x0_u.shape)}, m_u {tuple(m_u.shape)}"
        )
    device = next(net.parameters()).device
    x0_u, m_u = x0_u.to(device), m_u.to(device)
    autoencoder = autoencoder_of(net)
    if autoencoder is None:
        cond = stage_cond(x0_u, m_u)  # (B, [L,] 3, H, W)
        known = (x0_u, m_u) if pin_known else None
    else:  # a latent stage 2 reads (z_u, m_u on the latent); pinned pixels are pinned in the decoded scan
        cond = stage_cond(to_latent(autoencoder, x0_u), latent_mask(m_u, cfg.latent_factor))
        known = None
    batch_shape = tuple(x0_u.shape[:-3])
    sample = _sample(stage2, batch_shape, settings.steps, generator, cond, settings, motion, known, STAGE2_TASK)
    x0 = sample.x0
    if autoencoder is not None:
        x0 = from_latent(autoencoder, x0)
        x0 = torch.where(m_u.bool().expand_as(x0), x0_u, x0) if pin_known else x0
    return {"x0": x0, "x0_u": x0_u, "m_u": m_u}


def refine(
    detail: Loaded, x_low: Tensor, generator: Generators, settings: SamplingSettings = DEFAULT_SAMPLING
) -> dict[str, Tensor]:
    """A cascade's second level: x0 (B, 2, H, W) ~ p(x0 | the layout x_low (B, 2, H, W / s) on every s-th column)
    from a detail net (train-diffusion stage=detail, `u4d_aug.cascade`) at settings.steps -> dict(x0, x0_u, m_u),
    x0_u and m_u the placed layout columns."""
    _check_stage(detail, "detail", "detail")
    detail = with_mean_start(detail, "detail", settings)
    net, cfg = detail
    low_width = cfg.width // cfg.detail_stride
    if x_low.dim() != 4 or x_low.shape[1:] != (2, cfg.height, low_width):
        raise InputError(
            f"detail: this net completes {cfg.height}x{cfg.width} scans from layouts of {cfg.height}x{low_width} "
            f"(every {cfg.detail_stride}th column): expected x_low (B, 2, {cfg.height}, {low_width}), got "
            f"{tuple(x_low.shape)}"
        )
    device = next(net.parameters()).device
    x0_u, m = place_columns(x_low.to(device), cfg.detail_stride)
    sample = _sample(detail, (x_low.shape[0],), settings.steps, generator, stage_cond(x0_u, m), settings)
    return {"x0": sample.x0, "x0_u": x0_u, "m_u": m}


def generate_u4d(
    stage1: Loaded,
    stage2: Loaded,
    n: int,
    generator: Generators,
    settings: SamplingSettings = DEFAULT_SAMPLING,
    frames: int | None = None,
    motion: Tensor | None = None,
) -> dict[str, Tensor]:
    """Hard-to-easy: x0_u ~ stage 1 (mask from its head, at most settings.stage1_mask_fraction of the pixels), then
    x0 ~ stage 2 given it -> dict(x0, x0_u, m_u_pred); `settings` as `u4d generate` reads them (the defaults: those of
    configs/u4d/generate_hdl64.yaml, with the mean start of the nets' stored training means).

    Sequences have `frames` = L frames (None: stage 2's training L); stage 1 makes the same L frames. `motion`
    (n, L, 4) conditions whichever stages were trained with an ego-motion input.
    """
    (_, cfg1), (_, cfg2) = stage1, stage2
    if (cfg1.height, cfg1.width) != (cfg2.height, cfg2.width):
        raise InputError("stage 1 and stage 2 checkpoints were trained on different image sizes")
    frames = frames or cfg2.frames
    motion1 = motion if cfg1.net.pose_dim else None
    motion2 = motion if cfg2.net.pose_dim else None
    first = generate_stage1(stage1, n, generator, settings, frames=frames, motion=motion1)
    second = complete(stage2, first["x0_u"], first["m_u_pred"], generator, settings, motion=motion2)
    return {"x0": second["x0"], "x0_u": first["x0_u"], "m_u_pred": first["m_u_pred"]}


def _propagation_poses(poses: np.ndarray, n: int) -> np.ndarray:
    """(n, L, 4, 4) float64 LiDAR poses of n sequences of L >= 2 frames; InputError else."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 4 or poses.shape[0] != n or poses.shape[1] < 2 or poses.shape[2:] != (4, 4):
        raise InputError(f"propagation needs poses (n={n}, L >= 2, 4, 4), got {poses.shape}")
    return poses


def _warp_first_frames(x0: Tensor, poses: np.ndarray, cfg: DiffusionTrainConfig) -> tuple[Tensor, Tensor]:
    """Frame 0 of each sequence x0 (n, L, 2, H, W) moved along its poses (`warp_frame0`) -> x0_u, m_u (n, L, ...)."""
    sensor = get_sensor(cfg.sensor)
    warped = [warp_frame0(x0[i, 0], poses[i], sensor, cfg.row_mode) for i in range(len(poses))]
    return torch.stack([w[0] for w in warped]), torch.stack([w[1] for w in warped])


def generate_u4d_propagated(
    stage1: Loaded,
    stage2: Loaded,
    n: int,
    generator: Generators,
    poses: np.ndarray,
    settings: SamplingSettings = DEFAULT_SAMPLING,
    motion: Tensor | None = None,
    pin_known: bool = False,
) -> dict[str, Tensor]:
    """L-frame U4D sequences that follow their ego motion: `generate_u4d` draws frame 0, `warp_frame0` moves it into
    frames 1..L-1 along `poses` (n, L, 4, 4), stage 2 completes the pixels it does not reach (`pin_known`: with its
    x̂0 pinned to the warped pixels at every step); the warped pixels are kept as they are -> dict(x0, x0_u,
    m_u_pred) (n, L, ...), m_u_pred the warped region."""
    poses = _propagation_poses(poses, n)
    frames = poses.shape[1]
    first = generate_u4d(stage1, stage2, n, generator, settings, frames, motion)
    _, cfg2 = stage2
    x0_u, m_u = _warp_first_frames(first["x0"], poses, cfg2)  # (n, L, 2|1, H, W)
    motion2 = motion if cfg2.net.pose_dim else None
    second = complete(stage2, x0_u, m_u, generator, settings, motion=motion2, pin_known=pin_known)
    x0 = torch.where(m_u.bool(), x0_u.to(second["x0"].device), second["x0"])
    return {"x0": x0, "x0_u": x0_u, "m_u_pred": m_u}


def generate_baseline(
    net: Loaded,
    n: int,
    generator: Generators,
    settings: SamplingSettings = DEFAULT_SAMPLING,
    frames: int | None = None,
    motion: Tensor | None = None,
) -> dict[str, Tensor]:
    """R2DM-style unconditional x0 (n, [L,] 2, H, W) (L = `frames`, None: the frames the net was trained with) at
    settings.steps, from the stored mean with settings.mean_start_below (`with_mean_start`; the stage-1 settings
    are not read); `motion` (n, L, 4) for a net trained with an ego-motion input."""
    _check_stage(net, "baseline", "baseline")
    net = with_mean_start(net, "baseline", settings)
    _, cfg = net
    shape = _batch_shape(n, frames or cfg.frames)
    x0 = _sample(net, shape, settings.steps, generator, None, settings, motion).x0
    autoencoder = autoencoder_of(net[0])
    return {"x0": x0 if autoencoder is None else from_latent(autoencoder, x0)}


def generate_baseline_propagated(
    net: Loaded,
    n: int,
    generator: Generators,
    poses: np.ndarray,
    settings: SamplingSettings = DEFAULT_SAMPLING,
    motion: Tensor | None = None,
) -> dict[str, Tensor]:
    """L-frame baseline sequences that follow their ego motion: `generate_baseline` draws frame 0, `warp_frame0`
    moves it into frames 1..L-1 along `poses` (n, L, 4, 4), and a second pass of the unconditional net inpaints the
    pixels it does not reach by replacement (`replace_known`) -> dict(x0, x0_u, m_u_pred) (n, L, ...), m_u_pred the
    warped region. The single-stage counterpart of `generate_u4d_propagated`."""
    _check_stage(net, "baseline", "baseline")
    poses = _propagation_poses(poses, n)
    frames = poses.shape[1]
    first = generate_baseline(net, n, generator, settings, frames, motion)["x0"]  # (n, L, 2, H, W)
    _, cfg = net
    x0_u, m_u = _warp_first_frames(first, poses, cfg)  # (n, L, 2|1, H, W)
    x0 = inpaint(net, x0_u, m_u, generator, settings, motion)["x0"]
    return {"x0": x0, "x0_u": x0_u, "m_u_pred": m_u}


def inpaint(
    net: Loaded,
    x0_u: Tensor,
    m_u: Tensor,
    generator: Generators,
    settings: SamplingSettings = DEFAULT_SAMPLING,
    motion: Tensor | None = None,
) -> dict[str, Tensor]:
    """The baseline's completion: x0 (B, [L,] 2, H, W) of the unconditional net with x̂0 pinned to x0_u where m_u is 1
    (`replace_known`, RePaint-style without resampling) and x0_u exactly there; the single-stage counterpart of
    `complete`, with `settings` as `generate_baseline` reads them."""
    _check_stage(net, "baseline", "baseline")
    if autoencoder_of(net[0]) is not None:
        raise InputError(
            "inpainting (the baseline's completion and propagated sequences) pins pixels at every sampler step; a "
            "latent baseline has no pixels while it samples: use a range-image baseline"
        )
    net = with_mean_start(net, "baseline", settings)
    _, cfg = net
    if (
        x0_u.dim() not in (4, 5)
        or x0_u.shape[-3:] != (2, cfg.height, cfg.width)
        or m_u.shape != (*x0_u.shape[:-3], 1, cfg.height, cfg.width)
    ):
        raise InputError(
            f"the baseline was trained on {cfg.height}x{cfg.width} images: expected x0_u (B, [L,] 2, H, W) and m_u "
            f"(B, [L,] 1, H, W), got x0_u {tuple(x0_u.shape)}, m_u {tuple(m_u.shape)}"
        )
    batch_shape = tuple(x0_u.shape[:-3])
    sample = _sample(net, batch_shape, settings.steps, generator, None, settings, motion, known=(x0_u, m_u))
    x0 = torch.where(m_u.bool().to(sample.x0.device), x0_u.to(sample.x0.device), sample.x0)  # exact where known
    return {"x0": x0, "x0_u": x0_u, "m_u": m_u}


def to_points(x0: Tensor, sensor: Sensor | str, row_mode: RowMode = "beam") -> list[np.ndarray]:
    """Range images (B, [L,] 2, H, W) -> B·L point clouds (M, 4) float32 [x, y, z, reflectance], frames in order."""
    sensor = get_sensor(sensor) if not isinstance(sensor, Sensor) else sensor
    images = x0.detach().float().cpu().reshape(-1, *x0.shape[-3:])  # (B·L, 2, H, W)
    points, valid = unproject(images, sensor, row_mode)  # (B·L, H, W, 4), (B·L, H, W)
    return [p[v].numpy().astype(np.float32) for p, v in zip(points, valid)]
