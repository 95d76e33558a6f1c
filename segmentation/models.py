"""MinkUNet-like and SPVCNN-like segmentation nets on `segmentation.sparse` (no sparse library).

Layouts follow mmdet3d `MinkUNetBackbone` / `SPVCNNBackbone` (torchsparse; see
reference/segmentation_protocols.md §2): stem of two submanifold 3x3x3 convs, 4 encoder stages (kernel-2
stride-2 conv, then residual blocks), 4 decoder stages (kernel-2 transposed conv, concat with the encoder
skip, residual blocks), linear head. SPVCNN adds a full-resolution point branch fused after the bottleneck,
after decoder stage 2 and after the last decoder stage. Both nets take a list of variable-size scans (N_b, 4)
[x, y, z, intensity] and return per-point logits (sum N_b, K) for the original points, in order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch
from torch import nn

from segmentation.sparse import (
    SparseBatchNorm,
    SparseConv3d,
    SparseReLU,
    SparseTensor,
    point_voxel_coords,
    point_voxel_index,
    points_to_voxels,
    sparse_cat,
    voxelize,
    voxels_to_points,
)

IN_FEATURE_CHANNELS = {"xyzi": 4, "xyz": 3, "i": 1, "xyzir": 5, "local": 6}


@dataclass
class SegModelConfig:
    """Net choice and size; defaults are MinkUNet18-W32 at 0.05 m as in mmdet3d / LaserMix."""

    name: Literal["minkunet", "spvcnn"] = "minkunet"
    num_classes: int = 19
    voxel_size: float = 0.05  # metres; upstream 0.05, coarser (0.1-0.2) for CPU presets
    width: float = 1.0  # channel multiplier (0.5 = W16, 0.625 = W20)
    base_channels: int = 32  # stem output
    encoder_channels: tuple[int, ...] = (32, 64, 128, 256)
    decoder_channels: tuple[int, ...] = (256, 128, 96, 96)
    blocks: tuple[int, ...] = (2, 2, 2, 2)  # residual blocks per encoder stage ((2, 3, 4, 6) = MinkUNet34)
    decoder_blocks: tuple[int, ...] = (2, 2, 2, 2)  # residual blocks per decoder stage
    # xyz (m), intensity, r = range (m); "local": offset in the voxel, z, intensity, horizontal range (no x, y)
    in_features: Literal["xyzi", "xyz", "i", "xyzir", "local"] = "xyzi"
    dropout: float = 0.3  # SPVCNN: on the re-voxelised features after the first two fusions
    interpolation: Literal["trilinear", "nearest"] = "trilinear"  # SPVCNN voxels -> points
    # convolutions keep their gathered inputs for backward instead of gathering again (more memory, same result)
    keep_gathers: bool = False
    # MinkUNet: a point reads its voxel's logits ("voxel", mmdet3d) or the softmax of the 8 nearest voxel centres
    # interpolated trilinearly ("trilinear", torchsparse voxel_to_point), returned as log-probabilities
    readout: Literal["voxel", "trilinear"] = "voxel"

    def __post_init__(self) -> None:
        stages = len(self.encoder_channels)
        if stages < 1 or not (len(self.decoder_channels) == len(self.blocks) == len(self.decoder_blocks) == stages):
            raise ValueError(
                "encoder_channels, decoder_channels, blocks and decoder_blocks need the same length (stages)"
            )
        if self.name == "spvcnn" and stages < 2:
            raise ValueError("spvcnn needs at least 2 stages")
        if self.num_classes < 1 or self.voxel_size <= 0 or self.width <= 0:
            raise ValueError("num_classes, voxel_size and width must be positive")
        if min(self.blocks) < 1 or min(self.decoder_blocks) < 1:
            raise ValueError("blocks and decoder_blocks need at least 1 residual block per stage")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.readout not in ("voxel", "trilinear") or (self.name == "spvcnn" and self.readout != "voxel"):
            raise ValueError(
                f"readout must be 'voxel' or 'trilinear' (minkunet only; spvcnn reads points), got {self.readout!r}"
            )


def point_features(points: torch.Tensor, in_features: str, voxel_size: float = 1.0) -> torch.Tensor:
    """(N, >= 4) [x, y, z, intensity, ...] -> (N, C_in) network input features.

    "local" drops the absolute x, y (under the training's random rotation about z they only say where the scan
    was turned to) for what does not turn with the scan: (N, 6) [offset of the point from its voxel's centre in
    voxel units (3, in [-0.5, 0.5)), z (m), intensity, horizontal range / 10 m].
    """
    if in_features == "xyzi":
        return points[:, :4]
    if in_features == "xyz":
        return points[:, :3]
    if in_features == "i":
        return points[:, 3:4]
    if in_features == "xyzir":
        return torch.cat([points[:, :4], points[:, :3].norm(dim=1, keepdim=True)], dim=1)
    if in_features == "local":
        cell = points[:, :3] / voxel_size
        offset = cell - torch.floor(cell) - 0.5  # (N, 3)
        ground_range = points[:, :2].norm(dim=1, keepdim=True) / 10.0
        return torch.cat([offset, points[:, 2:4], ground_range], dim=1)
    raise ValueError(f"in_features must be one of {sorted(IN_FEATURE_CHANNELS)}, got {in_features!r}")


def _scale(channels: int, width: float) -> int:
    return max(1, round(channels * width))


def conv_bn_relu(in_channels: int, out_channels: int, kernel_size: int = 3, stride: int = 1) -> nn.Sequential:
    """Sparse conv + BatchNorm + ReLU (mmdet3d `TorchsparseConvModule`)."""
    return nn.Sequential(
        SparseConv3d(in_channels, out_channels, kernel_size, stride),
        SparseBatchNorm(out_channels),
        SparseReLU(),
    )


class ResidualBlock(nn.Module):
    """Basic residual block: conv3-BN-ReLU-conv3-BN + shortcut (1x1 conv + BN when channels change), ReLU."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            SparseConv3d(in_channels, out_channels, 3),
            SparseBatchNorm(out_channels),
            SparseReLU(),
            SparseConv3d(out_channels, out_channels, 3),
            SparseBatchNorm(out_channels),
        )
        self.shortcut = (
            nn.Identity()
            if in_channels == out_channels
            else nn.Sequential(SparseConv3d(in_channels, out_channels, 1), SparseBatchNorm(out_channels))
        )

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace(torch.relu(self.main(x).features + self.shortcut(x).features))


def _blocks(in_channels: int, out_channels: int, count: int) -> list[ResidualBlock]:
    return [ResidualBlock(in_channels, out_channels)] + [
        ResidualBlock(out_channels, out_channels) for _ in range(count - 1)
    ]


class VoxelUNet(nn.Module):
    """Stem + encoder + decoder of MinkUNet (mmdet3d `MinkUNetBackbone`), channels scaled by `width`."""

    def __init__(self, cfg: SegModelConfig) -> None:
        super().__init__()
        base = _scale(cfg.base_channels, cfg.width)
        enc = [base] + [_scale(c, cfg.width) for c in cfg.encoder_channels]
        dec = [enc[-1]] + [_scale(c, cfg.width) for c in cfg.decoder_channels]
        self.stages = len(cfg.encoder_channels)
        self.base_channels, self.encoder_channels, self.decoder_channels = base, enc[1:], dec[1:]
        in_channels = IN_FEATURE_CHANNELS[cfg.in_features]
        self.stem = nn.Sequential(conv_bn_relu(in_channels, base), conv_bn_relu(base, base))
        self.encoder = nn.ModuleList(
            nn.Sequential(conv_bn_relu(enc[i], enc[i], 2, 2), *_blocks(enc[i], enc[i + 1], cfg.blocks[i]))
            for i in range(self.stages)
        )
        self.up = nn.ModuleList(
            nn.Sequential(
                SparseConv3d(dec[i], dec[i + 1], 2, 2, transposed=True),
                SparseBatchNorm(dec[i + 1]),
                SparseReLU(),
            )
            for i in range(self.stages)
        )
        self.decoder = nn.ModuleList(
            nn.Sequential(*_blocks(dec[i + 1] + enc[-2 - i], dec[i + 1], cfg.decoder_blocks[i]))
            for i in range(self.stages)
        )
        for module in self.modules():
            if isinstance(module, SparseConv3d):
                module.keep_gathers = cfg.keep_gathers

    def encode(self, x: SparseTensor) -> tuple[SparseTensor, list[SparseTensor]]:
        """Encoder stages -> (bottleneck, skips finest first incl. the stem output)."""
        skips = [x]
        for stage in self.encoder:
            x = stage(x)
            skips.append(x)
        return x, skips[:-1]

    def decode_stage(self, i: int, x: SparseTensor, skips: list[SparseTensor]) -> SparseTensor:
        """Decoder stage i: transposed conv up, concat the skip at that stride, residual blocks."""
        return self.decoder[i](sparse_cat([self.up[i](x), skips[-1 - i]]))


def _batch(points: Sequence[torch.Tensor], device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """List of (N_b, D) scans -> (N, D) points on `device` and (N,) batch index."""
    if len(points) == 0:
        raise ValueError("the batch needs at least one scan")
    for b, p in enumerate(points):
        if p.ndim != 2 or p.shape[1] < 4 or p.shape[0] == 0:
            shape = tuple(p.shape)
            raise ValueError(f"scan {b}: expected a non-empty (N, >= 4) [x, y, z, intensity] tensor, got {shape}")
    batch = torch.cat([torch.full((p.shape[0],), b, dtype=torch.int64) for b, p in enumerate(points)])
    return torch.cat([p.float() for p in points]).to(device), batch.to(device)


class VoxelLogits(NamedTuple):
    """Logits of the occupied finest-grid voxels of a batch, sorted by (batch, x, y, z)."""

    logits: torch.Tensor  # (M, K)
    inverse: torch.Tensor  # (N,) voxel row of every input point; point logits = logits[inverse]
    batch: torch.Tensor  # (M,) int64 scan index of every voxel (non-decreasing)


class MinkUNet(nn.Module):
    """MinkUNet-like voxel U-Net; each point reads the logits of its voxel (mmdet3d `point2voxel_map`)."""

    def __init__(self, cfg: SegModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.unet = VoxelUNet(cfg)
        self.head = nn.Linear(self.unet.decoder_channels[-1], cfg.num_classes)

    def forward(self, points: Sequence[torch.Tensor], voxel_output: bool = False) -> torch.Tensor | VoxelLogits:
        """List of (N_b, >= 4) scans -> (sum N_b, K) logits, points in input order.

        voxel_output=True returns the voxels' logits with the point -> voxel map instead (loss.level "voxel").
        readout "trilinear": the point logits are log p with p (N, K) the voxels' softmax interpolated over the 8
        nearest voxel centres (absent ones renormalised away), so softmax(logits) = p.
        """
        xyzi, batch = _batch(points, self.head.weight.device)
        x, inverse = voxelize(
            xyzi, self.cfg.voxel_size, batch, point_features(xyzi, self.cfg.in_features, self.cfg.voxel_size)
        )
        x = self.unet.stem(x)
        x, skips = self.unet.encode(x)
        for i in range(self.unet.stages):
            x = self.unet.decode_stage(i, x, skips)
        logits = self.head(x.features)  # (M, K)
        if voxel_output:
            return VoxelLogits(logits, inverse, x.coords[:, 0])
        if self.cfg.readout == "trilinear":
            positions = xyzi[:, :3] / self.cfg.voxel_size  # (N, 3) in voxel units
            probs = voxels_to_points(x.replace(torch.softmax(logits, dim=1)), positions, batch, "trilinear")
            return probs.clamp_min(1e-12).log()  # (N, K)
        return logits[inverse]  # (N, K)


class SPVCNN(nn.Module):
    """SPVCNN-like: the U-Net plus a point branch (Tang et al., ECCV 2020; mmdet3d `SPVCNNBackbone`).

    At each fusion z <- devoxelize(voxels) + MLP(z_prev) (Linear+BN+ReLU); the first two fused point features
    are scattered back (mean) onto the voxels and dropped out (p = cfg.dropout). The head reads points.
    """

    def __init__(self, cfg: SegModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.unet = VoxelUNet(cfg)
        self.fuse_after = len(cfg.decoder_channels) // 2 - 1  # after decoder stage 2 of 4
        base, enc, dec = self.unet.base_channels, self.unet.encoder_channels, self.unet.decoder_channels
        self.point_mlps = nn.ModuleList(
            nn.Sequential(nn.Linear(a, b), nn.BatchNorm1d(b), nn.ReLU())
            for a, b in [(base, enc[-1]), (enc[-1], dec[self.fuse_after]), (dec[self.fuse_after], dec[-1])]
        )
        self.dropout = nn.Dropout(cfg.dropout)
        self.head = nn.Linear(dec[-1], cfg.num_classes)

    def forward(self, points: Sequence[torch.Tensor]) -> torch.Tensor:
        """List of (N_b, >= 4) scans -> (sum N_b, K) logits, points in input order."""
        cfg = self.cfg
        xyzi, batch = _batch(points, self.head.weight.device)
        positions = xyzi[:, :3] / cfg.voxel_size  # (N, 3) in voxel units
        coords = point_voxel_coords(xyzi[:, :3], batch, cfg.voxel_size)  # (N, 4)
        x, inverse = voxelize(xyzi, cfg.voxel_size, batch, point_features(xyzi, cfg.in_features, cfg.voxel_size))
        x = self.unet.stem(x)
        z = voxels_to_points(x, positions, batch, cfg.interpolation)  # z0 (N, base)
        x = points_to_voxels(z, x, inverse)
        x, skips = self.unet.encode(x)
        z = voxels_to_points(x, positions, batch, cfg.interpolation) + self.point_mlps[0](z)  # z1
        x = self._revoxelize(z, x, coords)
        for i in range(self.unet.stages):
            x = self.unet.decode_stage(i, x, skips)
            if i == self.fuse_after:
                z = voxels_to_points(x, positions, batch, cfg.interpolation) + self.point_mlps[1](z)  # z2
                x = self._revoxelize(z, x, coords)
        z = voxels_to_points(x, positions, batch, cfg.interpolation) + self.point_mlps[2](z)  # z3
        return self.head(z)  # (N, K)

    def _revoxelize(self, z: torch.Tensor, like: SparseTensor, coords: torch.Tensor) -> SparseTensor:
        x = points_to_voxels(z, like, point_voxel_index(like, coords))
        return x.replace(self.dropout(x.features))


def build_model(cfg: SegModelConfig) -> MinkUNet | SPVCNN:
    """The net named by cfg.name."""
    if cfg.name == "minkunet":
        return MinkUNet(cfg)
    elif cfg.name == "spvcnn":
        return SPVCNN(cfg)
    raise ValueError(f"model name must be one of 'minkunet', 'spvcnn'; got {cfg.name!r}")
