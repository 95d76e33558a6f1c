"""Range-image UNet blocks: ring convolutions, log-SNR embedding, AdaGN ResBlock, attention, ray features.

Follows R2DM `models/efficient_unet.py` + `models/ops.py` (generation_protocols.md §2.1): circular padding
along azimuth (W) and zero padding along elevation (H) in every 3×3 conv and in down/upsampling, AdaGN
scale-shift from a sinusoidal embedding of log-SNR, zero-initialised residual outputs, Fourier features of
the ray angles.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from u4d_aug.errors import InputError


class RingConv2d(nn.Conv2d):
    """Conv2d, circular padding along azimuth (W), zero padding along elevation (H) (R2DM `ops.Pad`).

    Same result as convolving `cat(x[..., -1:], x, x[..., :1])` with zero padding along H only, but without
    copying the whole activation: the conv zero-pads both axes and then the one or two seam columns are
    recomputed from 3-column strips that wrap around (whole UNet 1-6 % faster on CPU than padding by copy).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, stride: int = 1, bias: bool = True):
        if kernel_size not in (1, 3):
            raise ValueError(f"RingConv2d: kernel_size must be 1 or 3, got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=kernel_size // 2, bias=bias)

    def forward(self, x: Tensor) -> Tensor:  # (N, C, H, W) -> (N, C', H/stride, W/stride)
        out = super().forward(x)
        if self.kernel_size[0] == 1:
            return out
        width, stride = x.shape[-1], self.stride[1]
        if width < 3:
            raise ValueError(f"RingConv2d: width {width} is too small for a ring (need >= 3 columns)")
        # output column 0 reads input columns -1, 0, 1; the last one reads up to (W_out - 1)·stride + 1
        out[..., :1] = self._strip(torch.cat([x[..., -1:], x[..., :2]], dim=-1))
        last = (out.shape[-1] - 1) * stride
        if last + 1 >= width:
            out[..., -1:] = self._strip(torch.cat([x[..., last - 1 :], x[..., : last + 2 - width]], dim=-1))
        return out

    def _strip(self, strip: Tensor) -> Tensor:
        """One seam column: (N, C, H, 3) -> (N, C', H/stride, 1), zero padding along H only."""
        return F.conv2d(strip, self.weight, self.bias, stride=self.stride, padding=(1, 0))


class Downsample(nn.Module):
    """Halve H and W with a stride-2 ring conv (equivariant to azimuth rolls by an even number of columns)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = RingConv2d(channels, channels, 3, stride=2)

    def forward(self, x: Tensor) -> Tensor:  # (N, C, H, W) -> (N, C, H/2, W/2)
        return self.conv(x)


class Upsample(nn.Module):
    """Double H and W: nearest-neighbour repeat, then a ring conv (no checkerboard, ring topology kept)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = RingConv2d(channels, channels, 3)

    def forward(self, x: Tensor) -> Tensor:  # (N, C, H, W) -> (N, C, 2H, 2W)
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))


def sinusoidal_embedding(x: Tensor, dim: int, max_period: float = 10_000.0) -> Tensor:
    """Transformer sinusoids of a per-sample scalar (here log-SNR in [-15, 15], as R2DM): (N,) -> (N, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=x.device, dtype=torch.float32) / half)
    args = x.float()[:, None] * freqs[None, :]  # (N, half)
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = F.pad(emb, (0, 1))
    return emb


class NoiseLevelEmbedding(nn.Module):
    """Sinusoidal embedding of log-SNR followed by Linear-SiLU-Linear (DDPM / R2DM timestep MLP)."""

    def __init__(self, base_channels: int, embed_channels: int):
        super().__init__()
        self.base_channels = base_channels
        self.mlp = nn.Sequential(
            nn.Linear(base_channels, embed_channels), nn.SiLU(), nn.Linear(embed_channels, embed_channels)
        )

    def forward(self, log_snr: Tensor) -> Tensor:  # (N,) -> (N, E)
        return self.mlp(sinusoidal_embedding(log_snr, self.base_channels))


class PoseEmbedding(nn.Module):
    """Ego motion of a frame (P,) -> an addition to its noise-level embedding (E,): Fourier features, MLP.

    Each pose component (metres, radians) is read at octave frequencies 2^k·π/16, k = 0..5 (periods 32 m down to
    1 m; 0.1 rad resolves at the top octave), then Linear-SiLU-Linear. The last Linear starts at zero, so a net
    with the pose condition starts as the same function as one without.
    """

    octaves = 6

    def __init__(self, pose_dim: int, embed_channels: int):
        super().__init__()
        self.register_buffer("freqs", (2.0 ** torch.arange(self.octaves)) * (math.pi / 16.0), persistent=False)
        self.mlp = nn.Sequential(
            nn.Linear(2 * self.octaves * pose_dim, embed_channels), nn.SiLU(), nn.Linear(embed_channels, embed_channels)
        )
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, poses: Tensor) -> Tensor:  # (N, P) -> (N, E)
        args = poses.float()[:, :, None] * self.freqs  # (N, P, K)
        return self.mlp(torch.cat([torch.sin(args), torch.cos(args)], dim=-1).flatten(1))


def group_norm(channels: int, groups: int, affine: bool = True) -> nn.GroupNorm:
    """GroupNorm with a clear error when `channels` is not divisible by `groups`."""
    if channels % groups != 0:
        raise InputError(f"net.gn_groups={groups} must divide every channel count; {channels} is not divisible")
    return nn.GroupNorm(groups, channels, eps=1e-6, affine=affine)


def ada_group_norm(x: Tensor, groups: int, scale: Tensor, shift: Tensor, eps: float) -> Tensor:
    """GroupNorm with per-sample affine, (N, C, H, W), scale/shift (N, C): one fused kernel instead of three.

    Folding the batch into the channels makes the per-sample scale and shift an ordinary per-channel affine.
    """
    n, c = x.shape[:2]
    out = F.group_norm(x.reshape(1, n * c, *x.shape[2:]), n * groups, scale.reshape(-1), shift.reshape(-1), eps)
    return out.reshape(x.shape)


class ResBlock(nn.Module):
    """GN-SiLU-conv, AdaGN h·(1+scale)+shift, SiLU-dropout-conv (zero init), skip, ×1/√2 (R2DM ResBlock)."""

    def __init__(self, in_channels: int, out_channels: int, embed_channels: int, groups: int, dropout: float = 0.0):
        super().__init__()
        self.norm1 = group_norm(in_channels, groups)
        self.conv1 = RingConv2d(in_channels, out_channels, 3)
        self.embed = nn.Linear(embed_channels, 2 * out_channels)
        self.norm2 = group_norm(out_channels, groups, affine=False)  # AdaGN supplies scale and shift
        self.dropout = nn.Dropout(dropout)
        self.conv2 = RingConv2d(out_channels, out_channels, 3)
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)
        self.skip = nn.Conv2d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: Tensor, emb: Tensor) -> Tensor:  # x (N, C, H, W), emb (N, E) already SiLU-activated
        h = self.conv1(F.silu(self.norm1(x)))
        scale, shift = self.embed(emb).chunk(2, dim=1)  # (N, C') each
        h = ada_group_norm(h, self.norm2.num_groups, 1.0 + scale, shift, self.norm2.eps)
        h = self.conv2(self.dropout(F.silu(h)))
        return (self.skip(x) + h) * (1.0 / math.sqrt(2.0))


class AttentionBlock(nn.Module):
    """Multi-head self-attention over all H·W pixels, zero-init output, residual ×1/√2 (R2DM lowest level)."""

    def __init__(self, channels: int, groups: int, num_heads: int):
        super().__init__()
        if channels % num_heads != 0:
            raise InputError(f"net.attention_heads={num_heads} must divide the lowest-level width {channels}")
        self.num_heads = num_heads
        self.norm = group_norm(channels, groups)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.proj = nn.Conv2d(channels, channels, 1)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, x: Tensor) -> Tensor:  # (N, C, H, W)
        n, c, h, w = x.shape
        qkv = self.qkv(self.norm(x)).reshape(n, 3, self.num_heads, c // self.num_heads, h * w)
        # contiguous (N, heads, H·W, C/heads) operands: the CPU kernel is ~3× slower on transposed views
        q, k, v = qkv.transpose(-1, -2).contiguous().unbind(1)
        out = F.scaled_dot_product_attention(q, k, v)  # (N, heads, H·W, C/heads)
        out = out.transpose(-1, -2).reshape(n, c, h, w)
        return (x + self.proj(out)) * (1.0 / math.sqrt(2.0))


def num_fourier_frequencies(size: int) -> int:
    """R2DM's octave count per axis: ceil(log2(size)) (6 for 64 rows, 10 for 1024 columns)."""
    return max(1, math.ceil(math.log2(size)))


def ray_fourier_features(elevation: Tensor, azimuth: Tensor) -> Tensor:
    """Fourier features of ray angles: (H,), (W,) radians -> (2·(L_h+L_w), H, W) (R2DM coords encoding).

    Azimuth is used in radians with integer frequencies 2^k, so every feature is 2π-periodic and the ring
    topology is kept. Elevation is mapped affinely from its own span onto [-π/2, π/2] (injective even at the
    lowest frequency, keeps non-uniform beam spacing), then the same octaves; the top octave has a period of
    about two pixels along both axes.
    """
    elevation = elevation.detach().double().flatten()
    azimuth = azimuth.detach().double().flatten()
    height, width = elevation.numel(), azimuth.numel()
    span = (elevation.max() - elevation.min()).clamp_min(1e-12)
    elev = (elevation - elevation.min()) / span * math.pi - math.pi / 2  # (H,) in [-π/2, π/2]
    freq_h = 2.0 ** torch.arange(num_fourier_frequencies(height), dtype=torch.float64)
    freq_w = 2.0 ** torch.arange(num_fourier_frequencies(width), dtype=torch.float64)
    arg_h = freq_h[:, None] * elev[None, :]  # (L_h, H)
    arg_w = freq_w[:, None] * azimuth[None, :]  # (L_w, W)
    feat_h = torch.cat([torch.sin(arg_h), torch.cos(arg_h)])[:, :, None].expand(-1, height, width)
    feat_w = torch.cat([torch.sin(arg_w), torch.cos(arg_w)])[:, None, :].expand(-1, height, width)
    return torch.cat([feat_h, feat_w]).float().contiguous()


class RayFourierFeatures(nn.Module):
    """Fixed (C_ff, H, W) buffer of ray-angle Fourier features, projected by a 1×1 conv and added to the stem.

    The projection is linear and input independent, so it is computed once per forward and broadcast over the
    batch; a 1×1 conv is enough because the features are smooth positional codes (a 3×3 conv costs 9×).
    """

    def __init__(self, elevation: Tensor, azimuth: Tensor, out_channels: int):
        super().__init__()
        if elevation.dim() != 1 or azimuth.dim() != 1:
            raise InputError(
                f"ray angles must be 1-D (H,) elevation and (W,) azimuth, got {tuple(elevation.shape)} "
                f"and {tuple(azimuth.shape)}"
            )
        features = ray_fourier_features(elevation, azimuth)
        self.register_buffer("features", features)  # saved in checkpoints so a loaded net keeps its angles
        self.proj = nn.Conv2d(features.shape[0], out_channels, 1, bias=False)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.features.shape[1]), int(self.features.shape[2])

    def forward(self) -> Tensor:  # () -> (1, C, H, W)
        return self.proj(self.features[None])
