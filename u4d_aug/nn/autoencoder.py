"""RangeAutoencoder: a range image (2, H, W) <-> a latent (C_z, H/f, W/f) for latent diffusion (LiDM family).

LiDM (Ran et al., CVPR 2024) generates LiDAR scenes in the latent space of a range-image autoencoder: a diffusion
net that works on pixels spends its capacity on the exact depth of every pixel and leaves walls that scatter along
the rays, where a decoder trained to reconstruct scans puts locally coherent surfaces back. Layout of the LDM
first stage (Rombach et al. 2022, KL-regularised): ring-conv ResBlocks, stride-2 downsamples, a Gaussian posterior
(mean, log-variance) per latent pixel; the decoder mirrors it and ends in the image channels and a return-mask logit.
The forward returns the training losses (DESIGN §4.1): L1 on the returns' values, BCE of the mask, a small KL.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from u4d_aug.errors import InputError
from u4d_aug.nn.layers import Downsample, RingConv2d, Upsample, group_norm

NO_RETURN = -1.0  # the image value of a pixel without a return (DESIGN §3)


@dataclass
class AutoencoderConfig:
    """Widths of the RangeAutoencoder; the latent is (z_channels, H / f, W / f), f = 2^(levels - 1)."""

    in_channels: int = 2  # depth, reflectance
    base_channels: int = 32
    channel_multipliers: tuple[int, ...] = (1, 2, 4)  # one level each; a stride-2 downsample between levels
    num_res_blocks: int = 1  # per level, encoder and decoder
    z_channels: int = 8
    gn_groups: int = 8

    def __post_init__(self) -> None:
        if self.in_channels < 1 or self.base_channels < 1 or self.z_channels < 1 or self.num_res_blocks < 1:
            raise InputError(
                "autoencoder: in_channels, base_channels, z_channels and num_res_blocks must be >= 1, got "
                f"{self.in_channels}, {self.base_channels}, {self.z_channels}, {self.num_res_blocks}"
            )
        self.channel_multipliers = tuple(self.channel_multipliers)
        if not self.channel_multipliers or min(self.channel_multipliers) < 1:
            raise InputError(
                f"autoencoder.channel_multipliers must be positive integers, got {self.channel_multipliers}"
            )
        for width in (self.base_channels * m for m in self.channel_multipliers):
            if width % self.gn_groups:
                raise InputError(f"autoencoder.gn_groups={self.gn_groups} must divide every width; {width} does not")

    @property
    def factor(self) -> int:
        """How much smaller the latent is than the image along each axis."""
        return 2 ** (len(self.channel_multipliers) - 1)


class PlainResBlock(nn.Module):
    """GN-SiLU-conv twice with a skip, ×1/√2 (the ResBlock of `nn.layers` without the noise-level embedding)."""

    def __init__(self, in_channels: int, out_channels: int, groups: int):
        super().__init__()
        self.norm1 = group_norm(in_channels, groups)
        self.conv1 = RingConv2d(in_channels, out_channels, 3)
        self.norm2 = group_norm(out_channels, groups)
        self.conv2 = RingConv2d(out_channels, out_channels, 3)
        self.skip = nn.Conv2d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:  # (N, C, H, W) -> (N, C', H, W)
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return (self.skip(x) + h) * (1.0 / math.sqrt(2.0))


class RangeAutoencoder(nn.Module):
    """encode: (B, C, H, W) in [-1, 1] -> posterior mean and log-variance (B, C_z, H/f, W/f) each;
    decode: (B, C_z, H/f, W/f) -> values (B, C, H, W) and return-mask logits (B, 1, H, W)."""

    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        self.cfg = cfg
        widths = [cfg.base_channels * m for m in cfg.channel_multipliers]
        groups = cfg.gn_groups
        encoder: list[nn.Module] = [RingConv2d(cfg.in_channels, widths[0], 3)]
        for level, width in enumerate(widths):
            previous = widths[max(0, level - 1)]
            for index in range(cfg.num_res_blocks):
                encoder.append(PlainResBlock(previous if index == 0 else width, width, groups))
            if level < len(widths) - 1:
                encoder.append(Downsample(width))
        encoder += [PlainResBlock(widths[-1], widths[-1], groups), group_norm(widths[-1], groups), nn.SiLU()]
        encoder.append(RingConv2d(widths[-1], 2 * cfg.z_channels, 3))
        self.encoder = nn.Sequential(*encoder)
        decoder: list[nn.Module] = [
            RingConv2d(cfg.z_channels, widths[-1], 3),
            PlainResBlock(widths[-1], widths[-1], groups),
        ]
        for level in reversed(range(len(widths))):
            width = widths[level]
            for index in range(cfg.num_res_blocks):
                decoder.append(
                    PlainResBlock(widths[min(level + 1, len(widths) - 1)] if index == 0 else width, width, groups)
                )
            if level > 0:
                decoder.append(Upsample(width))
        decoder += [group_norm(widths[0], groups), nn.SiLU(), RingConv2d(widths[0], cfg.in_channels + 1, 3)]
        self.decoder = nn.Sequential(*decoder)
        # the latent a diffusion net sees is (mean − shift) / scale per channel, set from training scans once the
        # autoencoder is trained (`set_latent_statistics`), so it has zero mean and unit variance like the noise
        self.register_buffer("latent_shift", torch.zeros(cfg.z_channels))
        self.register_buffer("latent_scale", torch.ones(cfg.z_channels))

    def check_image(self, x: Tensor) -> None:
        """A clear error for an image the encoder cannot take: channels, or H and W not multiples of f."""
        factor = self.cfg.factor
        if x.dim() != 4 or x.shape[1] != self.cfg.in_channels:
            raise InputError(f"autoencoder: expected images (B, {self.cfg.in_channels}, H, W), got {tuple(x.shape)}")
        if x.shape[-2] % factor or x.shape[-1] % factor:
            raise InputError(f"autoencoder: image {x.shape[-2]}x{x.shape[-1]}: H and W must be multiples of {factor}")

    def encode(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and log-variance (clamped to [-30, 20], LDM) of images x (B, C, H, W)."""
        self.check_image(x)
        mean, logvar = self.encoder(x).chunk(2, dim=1)
        return mean, logvar.clamp(-30.0, 20.0)

    def decode(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """(values (B, C, H, W), mask logits (B, 1, H, W)) of latents z (B, C_z, h, w)."""
        if z.dim() != 4 or z.shape[1] != self.cfg.z_channels:
            raise InputError(f"autoencoder: expected latents (B, {self.cfg.z_channels}, h, w), got {tuple(z.shape)}")
        out = self.decoder(z)
        return out[:, :-1], out[:, -1:]

    def to_latent(self, x: Tensor) -> Tensor:
        """The normalised latent (B, C_z, H/f, W/f) of images x (B, C, H, W): (posterior mean − shift) / scale."""
        mean, _ = self.encode(x)
        return (mean - self.latent_shift.view(1, -1, 1, 1)) / self.latent_scale.view(1, -1, 1, 1)

    def from_latent(self, z: Tensor) -> Tensor:
        """The range image (B, C, H, W) of normalised latents z (B, C_z, h, w) (`decoded_image` of the decoder)."""
        z = z * self.latent_scale.view(1, -1, 1, 1) + self.latent_shift.view(1, -1, 1, 1)
        return decoded_image(*self.decode(z))

    @torch.no_grad()
    def set_latent_statistics(self, means: Tensor) -> None:
        """Set the latent's shift and scale to the per-channel mean and std of posterior means (N, C_z, h, w)."""
        self.latent_shift.copy_(means.mean(dim=(0, 2, 3)))
        self.latent_scale.copy_(means.std(dim=(0, 2, 3)).clamp(min=1e-6))

    def forward(
        self,
        x: Tensor,
        generator: torch.Generator | None = None,
        kl_weight: float = 1e-6,
        mask_weight: float = 1.0,
        column_weight: Tensor | None = None,
        value_weights: tuple[float, ...] | None = None,
    ) -> dict[str, Tensor]:
        """Losses of images x (B, C, H, W): "l1" of the values on the returns (x[:, 0] > −1), "mask_bce" of the
        return mask, "kl" to N(0, 1) per latent element, "loss" = l1 + mask_weight · mask_bce + kl_weight · kl;
        "l1_depth", the depth channel's L1 alone, is logged. The latent is drawn from the posterior with noise from
        `generator`; `column_weight` (W,) weighs the image losses per column (0 on a crop's margins), None = all 1;
        `value_weights` (C,) weighs the channels in the l1 (a weighted mean), None = all 1."""
        mean, logvar = self.encode(x)
        draw_device = generator.device if generator is not None else x.device
        noise = torch.randn(mean.shape, generator=generator, device=draw_device).to(mean.device, mean.dtype)
        values, logits = self.decode(mean + torch.exp(0.5 * logvar) * noise)
        returns = (x[:, :1] > NO_RETURN).to(x.dtype)  # (B, 1, H, W)
        weight = torch.ones_like(returns) if column_weight is None else column_weight.to(x).expand_as(returns)
        on_returns = returns * weight
        channels = torch.ones(x.shape[1]) if value_weights is None else torch.tensor(value_weights, dtype=torch.float32)
        if channels.shape != (x.shape[1],) or bool((channels < 0).any()) or float(channels.sum()) <= 0:
            raise InputError(
                f"autoencoder: value_weights must be {x.shape[1]} non-negative weights, got {value_weights}"
            )
        channels = channels.to(x).view(1, -1, 1, 1)
        error = (values - x).abs() * on_returns  # (B, C, H, W)
        count = on_returns.sum().clamp(min=1.0)
        l1 = (error * channels).sum() / (count * channels.sum())
        l1_depth = error[:, 0].sum() / count
        bce = F.binary_cross_entropy_with_logits(logits, returns, reduction="none")
        bce = (bce * weight).sum() / weight.sum().clamp(min=1.0)
        kl = 0.5 * (mean.square() + logvar.exp() - 1.0 - logvar).mean()
        loss = l1 + mask_weight * bce + kl_weight * kl
        return {
            "loss": loss,
            "l1": l1.detach(),
            "l1_depth": l1_depth.detach(),
            "mask_bce": bce.detach(),
            "kl": kl.detach(),
        }


def decoded_image(values: Tensor, mask_logits: Tensor) -> Tensor:
    """A decoder's output as a range image (B, C, H, W): the values clamped to [-1, 1] where the mask logit is
    positive, −1 (no return) elsewhere."""
    keep = (mask_logits > 0).expand_as(values)
    return torch.where(keep, values.clamp(-1.0, 1.0), torch.full_like(values, NO_RETURN))
