"""The contract of the range-image autoencoder (as `stage.py` is the diffusion stages'): its run's config, the net
factory and the weights file `u4d train-autoencoder` writes and latent generators read (OUT/autoencoder.pt)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch

from u4d_aug.config import config_from_dict, config_to_dict
from u4d_aug.data.nuscenes import NUSCENES_VERSION
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_torch_save, load_checkpoint
from u4d_aug.nn.autoencoder import AutoencoderConfig, RangeAutoencoder
from u4d_aug.range_view import RowMode
from u4d_aug.stage import DiffusionOptimConfig, UncertaintyConfig

WEIGHTS_KIND = "u4d-autoencoder"
WEIGHTS_NAME = "autoencoder.pt"


@dataclass
class AutoencoderOptimConfig(DiffusionOptimConfig):
    """The diffusion nets' AdamW and lr schedule at the autoencoder's default lr."""

    lr: float = 5e-4


@dataclass
class AutoencoderTrainConfig:
    """One autoencoder run: the scans (as train-diffusion reads them), the net, the losses, the loop."""

    data_root: str = ""  # SemanticKITTI layout, or a nuScenes root
    data_format: Literal["semantickitti", "nuscenes"] = "semantickitti"
    nuscenes_version: str = NUSCENES_VERSION
    sequences: list[str] | None = None  # None = all under data_root
    probs_root: str = ""  # `u4d seg-predict` probabilities; needed when uncertain_share > 0
    sensor: str = "hdl64"
    height: int = 64
    width: int = 1024
    row_mode: RowMode = "beam"
    crop_width: int = 256  # > 0: random azimuth crops of this many columns (a multiple of the latent factor); 0 = off
    crop_margin: int = 8  # crops: columns at each edge the losses skip (a crop's ring padding is a seam)
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)
    uncertain_share: float = 0.5  # the share of each batch that is x0_u images (U4D stage 1's), the rest full scans
    ae: AutoencoderConfig = field(default_factory=AutoencoderConfig)
    kl_weight: float = 1e-6  # LDM's KL-regularised first stage: a weak pull to N(0, 1)
    mask_weight: float = 1.0  # BCE of the return mask next to the L1 of the values
    value_weights: tuple[float, ...] = (1.0, 1.0)  # the L1's weight of each channel (depth, reflectance)
    optim: AutoencoderOptimConfig = field(default_factory=AutoencoderOptimConfig)
    steps: int = 4000
    max_minutes: float = 0.0  # wall-clock budget (0 = none)
    batch_size: int = 4
    stats_scans: int = 64  # training scans whose latents set the latent's shift and scale at the end
    log_every: int = 50
    checkpoint_every: int = 500
    keep_checkpoints: int = 2
    cache_images: bool = True
    seed: int = 0
    device: str = "auto"
    out: str = "runs/autoencoder"

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch_size < 1 or self.stats_scans < 1:
            raise InputError(f"steps, batch_size and stats_scans must be >= 1, got {self.steps}, {self.batch_size}, "
                             f"{self.stats_scans}")  # fmt: skip
        factor = self.ae.factor
        if self.height % factor or self.width % factor:
            raise InputError(f"height/width {self.height}x{self.width} must be multiples of the latent factor {factor}")
        if self.crop_width and not (0 < self.crop_width <= self.width and self.crop_width % factor == 0):
            raise InputError(f"crop_width must be 0 (off) or a multiple of {factor} up to width {self.width}, "
                             f"got {self.crop_width}")  # fmt: skip
        if self.crop_margin < 0 or 4 * self.crop_margin >= (self.crop_width or self.width):
            raise InputError(f"crop_margin must be >= 0 and below a quarter of the crop, got {self.crop_margin}")
        if not 0.0 <= self.uncertain_share < 1.0:
            raise InputError(f"uncertain_share must be in [0, 1), got {self.uncertain_share}")
        self.value_weights = tuple(float(w) for w in self.value_weights)
        if (
            len(self.value_weights) != self.ae.in_channels
            or min(self.value_weights) < 0
            or sum(self.value_weights) <= 0
        ):
            raise InputError(
                f"value_weights: expected {self.ae.in_channels} non-negative weights (one per channel, not all 0), "
                f"got {list(self.value_weights)}"
            )
        if self.kl_weight < 0 or self.mask_weight < 0:
            raise InputError(f"kl_weight and mask_weight must be >= 0, got {self.kl_weight}, {self.mask_weight}")


def build_autoencoder(cfg: AutoencoderConfig, seed: int) -> RangeAutoencoder:
    """A RangeAutoencoder initialised from `seed` without touching the caller's global RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return RangeAutoencoder(cfg)


def save_autoencoder(path: Path, net: RangeAutoencoder, cfg: AutoencoderTrainConfig) -> None:
    """The trained autoencoder's weights (with the latent statistics) and its run's config, written atomically."""
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    atomic_torch_save(path, {"kind": WEIGHTS_KIND, "config": config_to_dict(cfg), "model": state})


def load_autoencoder(
    path: str | Path, device: torch.device | str = "cpu"
) -> tuple[RangeAutoencoder, AutoencoderTrainConfig]:
    """(autoencoder in eval mode, its run's config) from OUT/autoencoder.pt or a run folder holding one."""
    path = Path(path)
    if path.is_dir():
        path = path / WEIGHTS_NAME
    state = load_checkpoint(path, "autoencoder weights")
    if state.get("kind") != WEIGHTS_KIND:
        raise InputError(f"{path}: not the autoencoder weights of `u4d train-autoencoder` (OUT/{WEIGHTS_NAME})")
    cfg = config_from_dict(AutoencoderTrainConfig, state.get("config") or {}, source=str(path))
    net = RangeAutoencoder(cfg.ae)
    try:
        net.load_state_dict(state["model"])
    except (KeyError, RuntimeError) as exc:
        raise InputError(f"{path}: its weights do not fit the autoencoder its config describes ({exc})") from None
    return net.to(device).eval(), cfg
