"""Latent generators (LiDM, Ran et al. 2024): a diffusion net on the latents of a trained `RangeAutoencoder`.

A latent generator's config names the autoencoder (`autoencoder`, `latent_factor`); training encodes each batch's
range images to latents (x0 -> z, x0_u -> z_u, the mask m_u -> the latent pixels it touches, max-pooled) and the
net learns them as a range-image net learns pixels; sampling decodes them (`u4d_aug.pipeline`). The paper's two
stages keep their roles: stage 1 generates z_u with the mask head at the latent's resolution, stage 2 z given
(z_u, m_u) — the hard region first, then the scan.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from u4d_aug.autoencoder_stage import load_autoencoder
from u4d_aug.errors import InputError
from u4d_aug.nn.autoencoder import RangeAutoencoder
from u4d_aug.stage import DiffusionTrainConfig


def load_latent_autoencoder(cfg: DiffusionTrainConfig, device: torch.device | str = "cpu", base: Path | None = None):
    """The frozen autoencoder a latent generator's config names (a relative path is read from `base`, the folder of
    the generator's weights, when it is there), checked against the config's latent_factor and net channels."""
    path = Path(cfg.autoencoder)
    if not path.is_absolute() and base is not None and (base / path).exists():
        path = base / path
    if not path.exists():
        raise InputError(f"autoencoder: {path} does not exist (the `u4d train-autoencoder` OUT/autoencoder.pt)")
    autoencoder, ae_cfg = load_autoencoder(path, device)
    ae = ae_cfg.ae
    if ae.factor != cfg.latent_factor or ae.z_channels != cfg.net.in_channels or cfg.net.out_channels != ae.z_channels:
        raise InputError(
            f"autoencoder {path}: its latent is {ae.z_channels} channels at factor {ae.factor}; the generator's "
            f"config has latent_factor={cfg.latent_factor}, net.in_channels={cfg.net.in_channels}, "
            f"net.out_channels={cfg.net.out_channels} (set all three to the autoencoder's)"
        )
    if ae_cfg.sensor != cfg.sensor or ae_cfg.row_mode != cfg.row_mode or ae_cfg.height != cfg.height:
        raise InputError(
            f"autoencoder {path}: trained on {ae_cfg.sensor} {ae_cfg.height}-row images ({ae_cfg.row_mode}), the "
            f"generator on {cfg.sensor} {cfg.height}-row images ({cfg.row_mode})"
        )
    return autoencoder.requires_grad_(False)


def latent_mask(m_u: Tensor, factor: int) -> Tensor:
    """(..., 1, H, W) {0, 1} -> (..., 1, H/f, W/f): 1 where a latent pixel covers any pixel of the mask."""
    flat = m_u.reshape(-1, 1, *m_u.shape[-2:]).float()
    pooled = F.max_pool2d(flat, factor)
    return pooled.reshape(*m_u.shape[:-2], *pooled.shape[-2:])


def pixel_mask(m_latent: Tensor, factor: int) -> Tensor:
    """(..., 1, h, w) -> (..., 1, h·f, w·f): each latent pixel's value on its f x f pixels."""
    return m_latent.repeat_interleave(factor, dim=-2).repeat_interleave(factor, dim=-1)


def to_latent(autoencoder: RangeAutoencoder, images: Tensor) -> Tensor:
    """Normalised latents (..., C_z, h, w) of range images (..., C, H, W), frames folded into the batch."""
    flat = images.reshape(-1, *images.shape[-3:])
    with torch.no_grad():
        z = autoencoder.to_latent(flat)
    return z.reshape(*images.shape[:-3], *z.shape[-3:])


def from_latent(autoencoder: RangeAutoencoder, z: Tensor) -> Tensor:
    """Range images (..., C, H, W) of normalised latents (..., C_z, h, w) (`RangeAutoencoder.from_latent`)."""
    flat = z.reshape(-1, *z.shape[-3:])
    with torch.no_grad():
        images = autoencoder.from_latent(flat)
    return images.reshape(*z.shape[:-3], *images.shape[-3:])


def encode_item(autoencoder: RangeAutoencoder, factor: int, item: dict[str, Tensor]) -> dict[str, Tensor]:
    """One scan's training images (x0 (C, H, W)[, x0_u, m_u]) -> their latents (x0 -> z, x0_u -> z_u, m_u -> its
    latent mask), on the CPU (`batches.RangeImages` caches them)."""
    device = next(autoencoder.parameters()).device
    out = {"x0": to_latent(autoencoder, item["x0"][None].to(device))[0].cpu()}
    if "x0_u" in item:
        out["x0_u"] = to_latent(autoencoder, item["x0_u"][None].to(device))[0].cpu()
        out["m_u"] = latent_mask(item["m_u"], factor)
    return out


class LatentNet(nn.Module):
    """A latent generator as the samplers call it: the diffusion net's forward, with its autoencoder beside it (not
    in its state dict: the generator's weights stay the net's)."""

    def __init__(self, net: nn.Module, autoencoder: RangeAutoencoder) -> None:
        super().__init__()
        self.net = net
        self.__dict__["autoencoder"] = autoencoder  # not a submodule: state_dict, parameters and EMA skip it

    @property
    def cfg(self):
        return self.net.cfg

    def to(self, *args, **kwargs):  # the autoencoder moves with the net
        self.__dict__["autoencoder"] = self.autoencoder.to(*args, **kwargs)
        return super().to(*args, **kwargs)

    def forward(self, x_t: Tensor, log_snr: Tensor, cond: Tensor | None = None, **kwargs):
        return self.net(x_t, log_snr, cond, **kwargs)


def autoencoder_of(net: nn.Module) -> RangeAutoencoder | None:
    """The autoencoder of a loaded latent generator (a LatentNet, possibly inside a MeanStart), None for a
    range-image net."""
    while not isinstance(net, LatentNet) and isinstance(getattr(net, "net", None), nn.Module):
        net = net.net
    return net.autoencoder if isinstance(net, LatentNet) else None
