"""RangeUNet: ε-prediction UNet on range images: ring convs, AdaGN, optional mask head (R2DM family), MoST."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from u4d_aug.errors import InputError
from u4d_aug.nn.layers import (
    AttentionBlock,
    Downsample,
    NoiseLevelEmbedding,
    PoseEmbedding,
    RayFourierFeatures,
    ResBlock,
    RingConv2d,
    Upsample,
    group_norm,
)
from u4d_aug.nn.most import FUSIONS, Fusion, MoSTBlock


@dataclass
class UNetConfig:
    """Widths and heads of the RangeUNet (R2DM `ModelConfig`; defaults are a cheap CPU size)."""

    base_channels: int = 32
    channel_multipliers: tuple[int, ...] = (1, 2, 2, 4)
    num_res_blocks: int | tuple[int, ...] = 2  # one count for all levels, or one per level
    attention: bool = True  # self-attention at the lowest resolution only
    attention_heads: int = 4
    fourier_features: bool = True  # ray-angle Fourier features as extra input (needs the angles at build time)
    in_channels: int = 2  # x_t: depth, reflectance
    cond_channels: int = 0  # extra input channels, e.g. x0_u (2) + m_u (1) = 3 for stage 2
    out_channels: int = 2  # ε̂
    mask_head: bool = False  # stage 1: extra 1-channel logit output m_p
    dropout: float = 0.0
    gn_groups: int = 8
    most: bool = False  # MoST blocks (U4D §2): gated spatial/temporal mixing across the L frames of a sequence
    most_levels: tuple[int, ...] | None = None  # levels with a MoST (enc + dec; mid with the lowest); None = all
    most_kernel_t: int = 3  # taps of the temporal conv along L (odd; zero padding beyond the clip)
    most_gate_noise: float = 0.5  # std of the Gaussian noise on the gate logits in training
    most_fusion: Fusion = "gating"  # how a MoST block joins its branches: gating | cascade | add | concat
    pose_dim: int = 0  # > 0: each frame's ego motion (e.g. dx, dy, dz, dyaw from u4d_aug.trajectory) conditions it
    # > 0: the net serves that many tasks, told apart by a learned task embedding added to the noise-level embedding
    # (U4D's one net for both stages: task 0 = stage 1, the uncertain region; task 1 = stage 2, the completion)
    num_tasks: int = 0

    def __post_init__(self) -> None:
        if self.base_channels < 1:
            raise InputError(f"net.base_channels must be >= 1, got {self.base_channels}")
        if not self.channel_multipliers or min(self.channel_multipliers) < 1:
            raise InputError(f"net.channel_multipliers must be positive integers, got {self.channel_multipliers}")
        if isinstance(self.num_res_blocks, int):
            self.num_res_blocks = (self.num_res_blocks,) * len(self.channel_multipliers)
        self.num_res_blocks = tuple(self.num_res_blocks)
        if len(self.num_res_blocks) != len(self.channel_multipliers) or min(self.num_res_blocks) < 1:
            raise InputError(
                f"net.num_res_blocks must be >= 1 per level ({len(self.channel_multipliers)} levels), "
                f"got {self.num_res_blocks}"
            )
        if self.in_channels < 1 or self.out_channels < 1 or self.cond_channels < 0:
            raise InputError("net.in_channels/out_channels must be >= 1 and net.cond_channels >= 0")
        if not 0.0 <= self.dropout < 1.0:
            raise InputError(f"net.dropout must be in [0, 1), got {self.dropout}")
        if self.most_levels is not None:
            self.most_levels = tuple(sorted(set(self.most_levels)))
            if not self.most_levels or not all(0 <= lv < len(self.channel_multipliers) for lv in self.most_levels):
                raise InputError(
                    f"net.most_levels must name levels 0..{len(self.channel_multipliers) - 1} (or be null for all), "
                    f"got {self.most_levels}"
                )
        if self.pose_dim < 0:
            raise InputError(f"net.pose_dim must be >= 0 (0 = no ego-motion condition), got {self.pose_dim}")
        if self.num_tasks < 0:
            raise InputError(f"net.num_tasks must be >= 0 (0 = one task, no task embedding), got {self.num_tasks}")
        if self.most_kernel_t < 1 or self.most_kernel_t % 2 == 0:
            raise InputError(f"net.most_kernel_t must be a positive odd number, got {self.most_kernel_t}")
        if self.most_fusion not in FUSIONS:
            raise InputError(f"net.most_fusion must be one of {', '.join(FUSIONS)}, got {self.most_fusion!r}")
        if self.most_gate_noise < 0:
            raise InputError(f"net.most_gate_noise must be >= 0, got {self.most_gate_noise}")

    @property
    def downsampling_factor(self) -> int:
        """H and W must be multiples of this (2^(levels-1))."""
        return 2 ** (len(self.channel_multipliers) - 1)


def crop_columns(offsets: Tensor, width: int, full_width: int) -> Tensor:
    """Panorama columns of azimuth crops: offsets (N,) -> (N, width) = (offset + j) mod full_width."""
    return (offsets.long()[:, None] + torch.arange(width, device=offsets.device)[None, :]) % full_width


class LevelBlock(nn.Module):
    """One UNet stage entry: a ResBlock, then self-attention when `attention` and the config allow it."""

    def __init__(self, in_channels: int, out_channels: int, embed_channels: int, cfg: UNetConfig, attention: bool):
        super().__init__()
        self.res = ResBlock(in_channels, out_channels, embed_channels, cfg.gn_groups, cfg.dropout)
        self.attn = (
            AttentionBlock(out_channels, cfg.gn_groups, cfg.attention_heads) if attention and cfg.attention else None
        )

    def forward(self, x: Tensor, emb: Tensor) -> Tensor:  # (N, C, H, W), (N, E) -> (N, C', H, W)
        h = self.res(x, emb)
        return self.attn(h) if self.attn is not None else h


def _ray_features(
    cfg: UNetConfig, elevation: Tensor | None, azimuth: Tensor | None, channels: int
) -> RayFourierFeatures | None:
    """The ray-angle Fourier features of the stem (None when net.fourier_features is off)."""
    if not cfg.fourier_features:
        return None
    if elevation is None or azimuth is None:
        raise InputError(
            "net.fourier_features=true needs the ray angles: pass elevation (H,) and azimuth (W,) "
            "from u4d_aug.range_view.ray_angles(sensor, H, W, row_mode) or set "
            "net.fourier_features=false"
        )
    return RayFourierFeatures(elevation, azimuth, channels)


def _encoder(
    cfg: UNetConfig, widths: list[int], embed_channels: int
) -> tuple[nn.ModuleList, list[int], dict[int, int]]:
    """Per level `num_res_blocks` LevelBlocks, then a stride-2 downsample but at the lowest level; returns the blocks,
    the width of every skip they leave (the stem's first) and the index of each level's last LevelBlock."""
    down = nn.ModuleList()
    skip_widths = [widths[0]]
    width = widths[0]
    ends = {}
    for level, (out_width, blocks) in enumerate(zip(widths, cfg.num_res_blocks)):
        lowest = level == len(widths) - 1
        for _ in range(blocks):
            down.append(LevelBlock(width, out_width, embed_channels, cfg, attention=lowest))
            width = out_width
            skip_widths.append(width)
        ends[level] = len(down) - 1
        if not lowest:
            down.append(Downsample(width))
            skip_widths.append(width)
    return down, skip_widths, ends


def _decoder(
    cfg: UNetConfig, widths: list[int], skip_widths: list[int], embed_channels: int
) -> tuple[nn.ModuleList, dict[int, int]]:
    """Per level, lowest first, `num_res_blocks` + 1 LevelBlocks that each read one skip (taken from the end of
    `skip_widths` until none is left), then an upsample but at level 0; returns them and each level's last index."""
    up = nn.ModuleList()
    width = widths[-1]
    ends = {}
    for level in reversed(range(len(widths))):
        lowest = level == len(widths) - 1
        for _ in range(cfg.num_res_blocks[level] + 1):
            skip = skip_widths.pop()
            up.append(LevelBlock(width + skip, widths[level], embed_channels, cfg, attention=lowest))
            width = widths[level]
        ends[level] = len(up) - 1
        if level > 0:
            up.append(Upsample(width))
    assert not skip_widths
    return up, ends


def _zero_conv(in_channels: int, out_channels: int) -> RingConv2d:
    """A 3x3 ring conv with zero weights and bias: an output head that starts at 0."""
    conv = RingConv2d(in_channels, out_channels, 3)
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)
    return conv


class RangeUNet(nn.Module):
    """ε_θ(x_t, log-SNR, cond) on (B, C, H, W) or (B, L, C, H, W); returns (ε̂, mask logits or None).

    Layout follows DDPM/ADM: per level `num_res_blocks` ResBlocks and a stride-2 ring-conv downsample; every
    block output is a skip; the decoder has one extra block per level. Attention (if on) sits only at the
    lowest level, as in R2DM. Output convs are zero-initialised: an untrained net predicts ε̂ = 0, logit 0.
    With `most`, a MoST block follows the res blocks of each chosen level in the encoder and the decoder (and the
    mid blocks with the lowest level); they are built after every other module, so the other weights of a
    seeded net do not depend on `most`, and they start as the identity.
    """

    def __init__(self, cfg: UNetConfig, elevation: Tensor | None = None, azimuth: Tensor | None = None):
        super().__init__()
        self.cfg = cfg
        widths = [cfg.base_channels * m for m in cfg.channel_multipliers]
        embed_channels = 4 * cfg.base_channels
        self.embed = NoiseLevelEmbedding(cfg.base_channels, embed_channels)
        self.stem = RingConv2d(cfg.in_channels + cfg.cond_channels, widths[0], 3)
        self.ray_features: RayFourierFeatures | None = _ray_features(cfg, elevation, azimuth, widths[0])
        self.down, skip_widths, down_ends = _encoder(cfg, widths, embed_channels)
        self.mid = nn.ModuleList(
            [
                LevelBlock(widths[-1], widths[-1], embed_channels, cfg, attention=True),
                LevelBlock(widths[-1], widths[-1], embed_channels, cfg, attention=False),
            ]
        )
        self.up, up_ends = _decoder(cfg, widths, skip_widths, embed_channels)
        self.out_norm = group_norm(widths[0], cfg.gn_groups)
        self.out_conv = _zero_conv(widths[0], cfg.out_channels)
        self.mask_conv: RingConv2d | None = _zero_conv(widths[0], 1) if cfg.mask_head else None
        # MoST blocks keyed by the index of the LevelBlock they follow, inserted in depth order (input -> output)
        self.most_down = nn.ModuleDict()
        self.most_mid = nn.ModuleDict()
        self.most_up = nn.ModuleDict()
        self.most_names: list[str] = []
        if cfg.most:
            self._add_most_blocks(widths, embed_channels, down_ends, up_ends)
        # built last for the same reason as the MoST blocks; zero-initialised output, so it starts as no condition
        self.pose_embed = PoseEmbedding(cfg.pose_dim, embed_channels) if cfg.pose_dim > 0 else None
        # built last too: a seeded net's other weights do not depend on num_tasks
        self.task_embed = nn.Embedding(cfg.num_tasks, embed_channels) if cfg.num_tasks > 0 else None

    def _add_most_blocks(
        self, widths: list[int], embed_channels: int, down_ends: dict[int, int], up_ends: dict[int, int]
    ) -> None:
        """A MoST block after the last LevelBlock of each chosen level, encoder then mid then decoder."""
        levels = range(len(widths)) if self.cfg.most_levels is None else self.cfg.most_levels
        for level in sorted(levels):
            self.most_down[str(down_ends[level])] = self._most_block(widths[level], embed_channels)
            self.most_names.append(f"enc{level}")
        if len(widths) - 1 in levels:
            self.most_mid[str(len(self.mid) - 1)] = self._most_block(widths[-1], embed_channels)
            self.most_names.append("mid")
        for level in sorted(levels, reverse=True):
            self.most_up[str(up_ends[level])] = self._most_block(widths[level], embed_channels)
            self.most_names.append(f"dec{level}")

    def _most_block(self, channels: int, embed_channels: int) -> MoSTBlock:
        cfg = self.cfg
        return MoSTBlock(
            channels, embed_channels, cfg.most_kernel_t, cfg.most_gate_noise, cfg.gn_groups, fusion=cfg.most_fusion
        )

    def most_blocks(self) -> list[MoSTBlock]:
        """The MoST blocks in depth order (input -> output), named by `most_names`; empty without `most`."""
        return [*self.most_down.values(), *self.most_mid.values(), *self.most_up.values()]

    def gate_weights(self) -> Tensor:
        """(M, 2) batch-mean (α^s, α^t) of each MoST block in the last forward, depth order; (0, 2) without MoST."""
        rows = [block.last_gates.float().mean(dim=0) for block in self.most_blocks() if block.last_gates is not None]
        return torch.stack(rows) if rows else torch.zeros(0, 2)

    def branch_updates(self) -> Tensor:
        """(M, 3) RMS of (x, α^s F^s, α^t F^t) per gated MoST block in the last forward with `record_updates` set."""
        rows = [block.last_updates for block in self.most_blocks() if block.last_updates is not None]
        return torch.stack(rows) if rows else torch.zeros(0, 3)

    def most_aux_loss(self) -> Tensor:
        """Σ over MoST blocks of CV² of the branch importances in the last forward (0 without MoST)."""
        terms = [block.last_cv for block in self.most_blocks() if block.last_cv is not None]
        return torch.stack(terms).sum() if terms else torch.zeros(())

    def forward(
        self,
        x_t: Tensor,
        log_snr: Tensor,
        cond: Tensor | None = None,
        generator: torch.Generator | None = None,
        crop_offsets: Tensor | None = None,
        poses: Tensor | None = None,
        task: Tensor | int | None = None,
    ) -> tuple[Tensor, Tensor | None]:
        """x_t (B, [L,] C_in, H, W), log_snr (B,) or (), cond (B, [L,] C_cond, H, W) -> (ε̂, mask logits).

        `poses` (B, [L,] pose_dim): each frame's ego motion, needed exactly when net.pose_dim > 0.
        `task` (B,) int or one int for the batch: which task each sample is, needed exactly when net.num_tasks > 0.
        `generator` draws the MoST gate noise in training mode (torch's CPU default generator if None).
        `crop_offsets` (B,) int: x_t is an azimuth crop of width W < the net's full width starting at these columns
        of the panorama (wrapping around); the ray features are read at the crop's columns (`crop_columns`) and the
        crop is padded as a ring of its own. None: x_t is the full panorama.
        """
        sequence = x_t.dim() == 5
        if x_t.dim() not in (4, 5):
            raise ValueError(f"RangeUNet: x_t must be (B, C, H, W) or (B, L, C, H, W), got {tuple(x_t.shape)}")
        batch = x_t.shape[0]
        log_snr = torch.as_tensor(log_snr, device=x_t.device, dtype=torch.float32).reshape(-1).expand(batch)
        if (poses is None) != (self.pose_embed is None):
            raise ValueError(f"RangeUNet: net.pose_dim = {self.cfg.pose_dim} needs poses exactly when it is > 0")
        if poses is not None and poses.shape != (*x_t.shape[:-3], self.cfg.pose_dim):
            raise ValueError(f"RangeUNet: poses must be (B, [L,] {self.cfg.pose_dim}), got {tuple(poses.shape)}")
        if (task is None) != (self.task_embed is None):
            raise ValueError(f"RangeUNet: net.num_tasks = {self.cfg.num_tasks} needs task exactly when it is > 0")
        if task is not None:
            # an int is checked as it is (so that a forward on the meta device, which sizes the net, never reads a
            # tensor's values); a tensor by its values
            out_of_range = (
                not 0 <= task < self.cfg.num_tasks
                if isinstance(task, int)
                else bool(((task < 0) | (task >= self.cfg.num_tasks)).any())
            )
            if out_of_range:
                shown = task if isinstance(task, int) else task.tolist()
                raise ValueError(f"RangeUNet: task must be in 0..{self.cfg.num_tasks - 1}, got {shown}")
            task = torch.as_tensor(task, device=x_t.device, dtype=torch.long).reshape(-1).expand(batch)
        frames = 1
        if sequence:
            # (B, L) is folded into the batch, frames of a sequence adjacent, and unfolded at the end; only the
            # MoST blocks (if any) look across the L frames.
            frames = x_t.shape[1]
            x_t = x_t.flatten(0, 1)
            cond = cond.flatten(0, 1) if cond is not None else None
            log_snr = log_snr.repeat_interleave(frames)
            crop_offsets = crop_offsets.repeat_interleave(frames) if crop_offsets is not None else None
            poses = poses.flatten(0, 1) if poses is not None else None
            task = task.repeat_interleave(frames) if task is not None else None
        eps, mask_logits = self._forward_frames(x_t, log_snr, cond, frames, generator, crop_offsets, poses, task)
        if sequence:
            eps = eps.unflatten(0, (batch, frames))
            mask_logits = mask_logits.unflatten(0, (batch, frames)) if mask_logits is not None else None
        return eps, mask_logits

    def _forward_frames(
        self,
        x_t: Tensor,
        log_snr: Tensor,
        cond: Tensor | None,
        frames: int,
        generator: torch.Generator | None,
        crop_offsets: Tensor | None = None,
        poses: Tensor | None = None,
        task: Tensor | None = None,
    ) -> tuple[Tensor, Tensor | None]:
        cfg = self.cfg
        _, channels, height, width = x_t.shape
        if channels != cfg.in_channels:
            raise ValueError(f"RangeUNet: expected {cfg.in_channels} x_t channels, got {channels}")
        factor = cfg.downsampling_factor
        if height % factor or width % factor:
            raise InputError(f"range image {height}x{width}: H and W must be multiples of {factor} for this UNet")
        if cfg.cond_channels:
            if cond is None or cond.shape[1] != cfg.cond_channels or cond.shape[-2:] != x_t.shape[-2:]:
                got = None if cond is None else tuple(cond.shape)
                raise ValueError(f"RangeUNet: expected cond with {cfg.cond_channels} channels like x_t, got {got}")
            x_t = torch.cat([x_t, cond], dim=1)
        elif cond is not None:
            raise ValueError("RangeUNet: got cond but net.cond_channels = 0")

        emb = self.embed(log_snr)  # (N, E)
        if self.pose_embed is not None:
            emb = emb + self.pose_embed(poses)  # each frame its own ego motion
        if self.task_embed is not None:
            emb = emb + self.task_embed(task)  # (N, E): which stage this sample is
        emb = F.silu(emb)  # every ResBlock applies its own Linear after this SiLU
        h = self.stem(x_t)  # (N, C0, H, W)
        if self.ray_features is not None:
            full_height, full_width = self.ray_features.size
            if height != full_height or width > full_width or (width < full_width and crop_offsets is None):
                raise InputError(
                    f"range image {height}x{width} does not match the {self.ray_features.size} ray-angle grid the net "
                    "was built with (a narrower image is an azimuth crop and needs crop_offsets)"
                )
            features = self.ray_features()  # (1, C0, H, W_full)
            if crop_offsets is not None:
                columns = crop_columns(crop_offsets.to(features.device), width, full_width)  # (N, W)
                features = features[0][:, :, columns].permute(2, 0, 1, 3)  # (N, C0, H, W)
            h = h + features  # broadcast over the batch for the full panorama

        skips = [h]
        for index, block in enumerate(self.down):
            h = block(h, emb) if isinstance(block, LevelBlock) else block(h)
            if str(index) in self.most_down:
                h = self.most_down[str(index)](h, emb, frames, generator)
            skips.append(h)
        for index, block in enumerate(self.mid):
            h = block(h, emb)
            if str(index) in self.most_mid:
                h = self.most_mid[str(index)](h, emb, frames, generator)
        for index, block in enumerate(self.up):
            if isinstance(block, LevelBlock):
                h = block(torch.cat([h, skips.pop()], dim=1), emb)
            else:
                h = block(h)
            if str(index) in self.most_up:
                h = self.most_up[str(index)](h, emb, frames, generator)

        h = F.silu(self.out_norm(h))
        eps = self.out_conv(h)  # (N, C_out, H, W)
        mask_logits = self.mask_conv(h) if self.mask_conv is not None else None  # (N, 1, H, W)
        return eps, mask_logits
