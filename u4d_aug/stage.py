"""The contract of a diffusion stage: its training config, how its net is built, and how a checkpoint names both.

Imported by training (`u4d_aug.train`), inference (`u4d_aug.pipeline`) and generation (`u4d_aug.generate`), so none
of them imports another for it. Stage 1 learns x0_u (the projected uncertain region P_u) with a mask head (L_u),
stage 2 learns the full scan given concat(x0_u, m_u) (L_c), the baseline learns x0 unconditionally (R2DM).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import torch

from u4d_aug.cascade import check_stride
from u4d_aug.config import config_from_dict
from u4d_aug.data.datasets import DATASET_FORMATS
from u4d_aug.data.nuscenes import NUSCENES_VERSION
from u4d_aug.data.sensors import get_sensor
from u4d_aug.diffusion import DiffusionConfig, net_heads
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.nn.unet import RangeUNet, UNetConfig
from u4d_aug.range_view import RowMode, ray_angles
from u4d_aug.run import checkpoint_state as run_checkpoint_state
from u4d_aug.uncertainty import Strategy
from u4d_aug.validate import check_finite_config, check_positive

CHECKPOINT_KIND = "u4d-diffusion"


@dataclass
class UncertaintyConfig:
    """P_u selection (paper §2.1): k as a point count (int) or a fraction of the scan (float)."""

    k: int | float = 0.1
    strategy: Strategy = "entropy"


@dataclass
class DiffusionOptimConfig:
    """AdamW with linear warm-up, then a constant lr or a cosine decay to min_lr_ratio · lr at the run's last step
    (R2DM: lr 1e-4, batch 8, no weight decay, grad-norm clip 1, cosine decay to 0)."""

    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 0.0
    warmup_steps: int = 100
    grad_clip: float = 1.0  # max grad norm; 0 = off
    schedule: Literal["constant", "cosine"] = "constant"  # after the warm-up
    min_lr_ratio: float = 0.0  # cosine: the lr at the last step, as a share of lr

    def __post_init__(self) -> None:
        check_finite_config(self, "optim.")
        check_positive(self, "lr", prefix="optim.")
        check_positive(self, "weight_decay", "warmup_steps", "grad_clip", allow_zero=True, prefix="optim.")
        if self.schedule not in ("constant", "cosine"):
            raise InputError(f"optim.schedule must be 'constant' or 'cosine', got {self.schedule!r}")
        if not 0.0 <= self.min_lr_ratio <= 1.0:
            raise InputError(f"optim.min_lr_ratio must be in [0, 1], got {self.min_lr_ratio}")
        if not all(0.0 <= beta < 1.0 for beta in self.betas):
            raise InputError(f"optim.betas must be in [0, 1), got {list(self.betas)}")


@dataclass
class DiffusionTrainConfig:
    """One stage's training run; `net.mask_head` and `net.cond_channels` follow `diffusion.stage`."""

    data_root: str = ""  # SemanticKITTI layout: ROOT/sequences/XX/velodyne/NNNNNN.bin, or a nuScenes root
    # layout of data_root: "semantickitti", or "nuscenes" (the keyframes of the v1.0 tables under ROOT/<version>/)
    data_format: Literal["semantickitti", "nuscenes"] = "semantickitti"
    nuscenes_version: str = NUSCENES_VERSION  # data_format nuscenes: the table folder under data_root
    sequences: list[str] | None = None  # None = all under data_root (nuScenes: scene names, numbers or ranges)
    probs_root: str = ""  # PROBS/sequences/XX/probs/NNNNNN.npy from `u4d seg-predict` (stage1/stage2)
    sensor: str = "hdl64"  # hdl64 | hdl32 | sensor yaml
    height: int = 64
    width: int = 1024
    row_mode: RowMode = "beam"
    crop_width: int = 0  # > 0: train on random azimuth crops of this many columns (sampling stays full width); 0 = off
    # crops: the columns at each edge of a crop that the losses skip. A crop is padded as a ring of its own, so its
    # edges meet at a seam that the full panorama never has; the margin keeps that seam out of what the net learns
    crop_margin: int = 0
    # stage detail (a cascade's second net, `u4d_aug.cascade`): s, the layout net generates every s-th column
    # (width / s columns) and this net completes the others given them
    detail_stride: int = 4
    frames: int = 1  # L: scans per item; > 1 trains on L-frame windows of one sequence, (B, L, C, H, W)
    frame_stride: int = 1  # frames between the scans of a window
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)
    # stage 2 on L-frame windows: the share of windows (drawn per window and step) whose condition is frame 0 moved
    # along the window's poses (`propagate.warp_frame0`, what `generate ... propagate=true` hands stage 2) instead
    # of each frame's P_u; 0 = P_u only (the paper's condition)
    propagated_share: float = 0.0
    net: UNetConfig = field(default_factory=UNetConfig)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    optim: DiffusionOptimConfig = field(default_factory=DiffusionOptimConfig)
    ema_decay: float = 0.995
    ema_warmup_steps: int = 0
    steps: int = 1000
    max_minutes: float = 0.0  # wall-clock budget (0 = none): stop with a checkpoint once used, even before `steps`
    batch_size: int = 8  # per rank
    log_every: int = 50
    checkpoint_every: int = 500
    keep_checkpoints: int = 2  # 0 = keep all
    sample_every: int = 0  # 0 = no sample PNGs; else a DDPM sample of the EMA net every that many steps
    sample_steps: int = 32
    cache_images: bool = True  # keep the projected range images of the training scans in memory
    seed: int = 0
    device: str = "auto"
    out: str = "runs/u4d"
    # a trained net of the same stage (checkpoint, run folder or exported weights) whose EMA weights start this run
    # at step 0 (fine-tuning); what this net adds to it (MoST blocks, the pose embedding) starts as the identity
    init_from: str = ""
    # latent diffusion (LiDM): the `u4d train-autoencoder` weights (OUT/autoencoder.pt) whose latents the net learns,
    # and their factor f (the latent is H/f x W/f; net.in_channels = net.out_channels = its latent channels); the
    # range images above are encoded once per step, samples are decoded back; "" / 0 = the net learns range images
    autoencoder: str = ""
    latent_factor: int = 0

    def __post_init__(self) -> None:
        # a new net config, not an edit of the given one: a config copied with another stage (dataclasses.replace)
        # shares its net config with the original, whose net may already be built from it
        mask_head, cond_channels, num_tasks = net_heads(self.diffusion.stage, self.net.in_channels)
        self.net = dataclasses.replace(self.net, mask_head=mask_head, cond_channels=cond_channels, num_tasks=num_tasks)
        if self.data_format not in DATASET_FORMATS:
            raise InputError(f"data_format must be one of {', '.join(DATASET_FORMATS)}, got {self.data_format!r}")
        if self.steps < 1 or self.batch_size < 1:
            raise InputError(f"steps and batch_size must be >= 1, got {self.steps}, {self.batch_size}")
        if self.height < 1 or self.width < 1:
            raise InputError(f"height/width must be >= 1, got {self.height}x{self.width}")
        factor = self.net.downsampling_factor
        if self.crop_width and not (0 < self.crop_width <= self.width and self.crop_width % factor == 0):
            raise InputError(
                f"crop_width must be 0 (off) or a multiple of {factor} (the net's downsampling) up to width "
                f"{self.width}, got {self.crop_width}"
            )
        if self.crop_margin < 0 or (self.crop_margin and 4 * self.crop_margin >= (self.crop_width or self.width)):
            raise InputError(
                f"crop_margin must be >= 0 and below a quarter of crop_width {self.crop_width}, got {self.crop_margin}"
            )
        if self.crop_margin and not self.crop_width:
            raise InputError("crop_margin: the margin of azimuth crops needs crop_width > 0")
        if self.diffusion.stage == "detail":
            check_stride(self.width, self.detail_stride)
            if self.frames > 1 or self.latent_factor:
                raise InputError(
                    "stage detail completes single range-image scans: frames must be 1 and latent_factor 0, got "
                    f"frames={self.frames}, latent_factor={self.latent_factor}"
                )
        if self.diffusion.stage == "u4d" and self.batch_size < 2:
            raise InputError(
                f"stage u4d trains both stages in every batch: batch_size must be >= 2, got {self.batch_size}"
            )
        if self.frames < 1 or self.frame_stride < 1:
            raise InputError(f"frames and frame_stride must be >= 1, got {self.frames}, {self.frame_stride}")
        if not 0.0 <= self.propagated_share <= 1.0:
            raise InputError(f"key 'propagated_share' must be in [0, 1], got {self.propagated_share}")
        if self.propagated_share > 0 and (self.diffusion.stage not in ("stage2", "u4d") or self.frames < 2):
            raise InputError(
                "key 'propagated_share': the propagated condition is stage 2's on windows of frames >= 2, got "
                f"stage {self.diffusion.stage} with frames={self.frames}"
            )
        if bool(self.autoencoder) != (self.latent_factor > 0) or self.latent_factor < 0:
            raise InputError(
                "autoencoder and latent_factor: a latent generator sets both (the autoencoder's weights and its factor "
                f"f >= 1), a range-image one neither; got autoencoder={self.autoencoder!r}, "
                f"latent_factor={self.latent_factor}"
            )
        if self.latent_factor and self.propagated_share > 0:
            raise InputError(
                "propagated_share: the propagated condition is warped in range images; a latent generator "
                "(latent_factor > 0) trains on P_u only"
            )
        if self.latent_factor and (
            self.height % self.latent_factor or self.width % self.latent_factor or self.crop_width
        ):
            raise InputError(
                f"latent_factor {self.latent_factor}: height/width {self.height}x{self.width} must be multiples of it, "
                f"and crop_width 0 (the latent is learnt on the full ring), got crop_width={self.crop_width}"
            )
        check_finite_config(self)
        check_positive(self, "log_every", "checkpoint_every", "sample_steps")
        check_positive(self, "keep_checkpoints", "sample_every", "max_minutes", "ema_warmup_steps", allow_zero=True)
        if not 0.0 <= self.ema_decay <= 1.0:
            raise InputError(f"key 'ema_decay' must be in [0, 1], got {self.ema_decay}")


# the diffusion keys a fine-tune does not take from its source net (`init_from`): the stage is the run's own, and the
# MoST term weighs blocks a single-frame source does not have
NOT_INHERITED = ("stage", "most_cv_weight")


def diffusion_recipe(cfg: DiffusionConfig) -> dict[str, object]:
    """The diffusion settings a fine-tune should share with its source net: every key of `cfg` but `NOT_INHERITED`."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg) if f.name not in NOT_INHERITED}


def diffusion_overrides(cfg: DiffusionConfig) -> list[str]:
    """`diffusion.KEY=VALUE` overrides (values in yaml: null, 0.05, eps) that set a run's `diffusion_recipe` to cfg's,
    e.g. a 4D fine-tune's to its single-frame source's (scripts/temporal_queue.sh ONE_NET=1)."""
    return [f"diffusion.{key}={_yaml_scalar(value)}" for key, value in diffusion_recipe(cfg).items()]


def _yaml_scalar(value: object) -> str:
    """A number, bool, None or string as the yaml an override parses back to the same value (1e-05 -> 1.0e-05: YAML
    1.1 reads a float only with a dot and a signed exponent)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        mantissa, sep, exponent = repr(value).partition("e")  # python writes the exponent's sign: 1e-05, 1e+20
        return f"{mantissa}{'' if '.' in mantissa or not sep else '.0'}{sep}{exponent}"
    return str(value)


def build_net(cfg: DiffusionTrainConfig, device: torch.device | str = "cpu") -> RangeUNet:
    """RangeUNet of the config (initialised from cfg.seed), with the ray angles of its sensor for Fourier features;
    a latent generator's are the mean angles of the f x f pixels of each latent pixel."""
    elevation, azimuth = ray_angles(get_sensor(cfg.sensor), cfg.height, cfg.width, cfg.row_mode)
    if cfg.latent_factor:
        elevation = elevation.view(-1, cfg.latent_factor).mean(dim=1)
        azimuth = azimuth.view(-1, cfg.latent_factor).mean(dim=1)
    with torch.random.fork_rng(devices=[]):  # seeded init without touching the caller's global RNG
        torch.manual_seed(cfg.seed)
        net = RangeUNet(cfg.net, elevation.float(), azimuth.float())
    return net.to(device)


def checkpoint_state(
    cfg: DiffusionTrainConfig,
    step: int,
    net: RangeUNet,
    ema: EMA,
    optimizer: torch.optim.Optimizer | None = None,
    elapsed: float = 0.0,
) -> dict:
    """A train-diffusion checkpoint (`u4d_aug.run.checkpoint_state` of kind CHECKPOINT_KIND): resolved config, step,
    wall-clock seconds, model, EMA, optimizer (None: an untrained or test checkpoint), RNG."""
    return run_checkpoint_state(CHECKPOINT_KIND, cfg, step, elapsed, net, optimizer, ema)


def config_from_checkpoint(ckpt: dict, source: str) -> DiffusionTrainConfig:
    """The resolved DiffusionTrainConfig stored in a checkpoint."""
    if ckpt.get("kind") != CHECKPOINT_KIND:
        raise InputError(f"{source}: not a u4d train-diffusion checkpoint")
    config = ckpt.get("config")
    if not isinstance(config, dict):
        got = "none" if config is None else f"a {type(config).__name__}"
        raise InputError(f"{source}: 'config' must be the run's resolved settings (a mapping), got {got}")
    return config_from_dict(DiffusionTrainConfig, config, source=source)
