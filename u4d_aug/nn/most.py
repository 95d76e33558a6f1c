"""MoST (Mixture of Spatio-Temporal) block: a gated mix of a spatial and a temporal branch over L frames.

U4D paper §2 ("Mixture of Spatio-Temporal (MoST) Block" and its figure): features F_i (C_i, L, H_i, W_i) are split into
a spatial branch F^s (intra-frame conv) and a temporal branch F^t (conv along the frame axis L), fused as
F^fuse = α^s ⊙ F^s + α^t ⊙ F^t with gates from a shared MLP embedding, noise on the gates in training and a
coefficient-of-variation term against collapse onto one branch. The gating follows the noisy gating network of
Shazeer et al. (2017, "Outrageously Large Neural Networks", §2.1 and eq. 6-7) with two experts and no top-k
(k = 2 keeps both, so the mixture is soft); its noise has a fixed std instead of the learned Softplus(x·W_noise):
with soft gating only the importance loss is used, and nothing would keep a learned noise scale from decaying.

Inside the UNet the L frames of a sequence are adjacent in the batch: features are (B·L, C, H, W) and the block
is told `frames` = L. The block is residual, x + F^fuse, with zero-initialised branch convs, so a new block is
the identity and a net with MoST starts out as the same function as one without.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from u4d_aug.nn.layers import RingConv2d, group_norm


def cv_squared(importance: Tensor, eps: float = 1e-10) -> Tensor:
    """CV(Importance)² = Var / Mean² over the experts of (E,) importances (Shazeer et al. 2017, eq. 6)."""
    importance = importance.float()
    return importance.var(unbiased=False) / (importance.mean().square() + eps)


def temporal_conv(x: Tensor, weight: Tensor, bias: Tensor | None, frames: int) -> Tensor:
    """Conv along L with kernel (k_t, 1, 1), zero padding: (B·L, C, H, W), weight (C', k_t·C, 1, 1) -> (B·L, C', H, W).

    Equal to conv3d over (B, C, L, H, W); written as one 1×1 conv over the k_t shifted copies of the frames
    stacked on channels (block j of the weight reads frame l + j − k_t//2), which is ~3.5× faster on CPU.
    """
    kernel_t = weight.shape[1] // x.shape[1]
    half = kernel_t // 2
    seq = x.unflatten(0, (x.shape[0] // frames, frames))  # (B, L, C, H, W)
    padded = F.pad(seq, (0, 0, 0, 0, 0, 0, half, half))  # (B, L + k_t − 1, C, H, W), zeros beyond the clip
    stacked = torch.cat([padded[:, j : j + frames] for j in range(kernel_t)], dim=2)  # (B, L, k_t·C, H, W)
    return F.conv2d(stacked.flatten(0, 1), weight, bias)


Fusion = Literal["gating", "cascade", "add", "concat"]
FUSIONS: tuple[str, ...] = ("gating", "cascade", "add", "concat")


class MoSTBlock(nn.Module):
    """x + α^s ⊙ F^s + α^t ⊙ F^t on (B·L, C, H, W) with per-sequence gates (α^s, α^t) (U4D MoST block).

    `fusion` picks the paper's ablation of how the branches meet (U4D §4, MoST fusion): "gating" (the block above),
    "cascade" (spatial then temporal: h = x + F^s(x), out = h + F^t(h)), "add" (x + F^s + F^t) or "concat"
    (x + 1×1 conv of concat(F^s, F^t)); only "gating" has gates, the others leave `last_gates`/`last_cv` None.

    F^s = RingConv3×3(SiLU(GN(x))) (circular along azimuth as the rest of the UNet), F^t = the k_t-tap temporal
    conv of the same activation. Gate logits = MLP(concat(mean of x over L, H, W; mean over L of the timestep
    embedding)), plus N(0, noise_std²) in training mode only; softmax over the two branches. After each
    forward, `last_gates` (B, 2) holds (α^s, α^t) (detached) and `last_cv` the CV² of their batch sums (with
    grad, for the loss). With `record_updates` set (analysis, `u4d gates`), `last_updates` (3,) also holds the RMS of
    x, α^s ⊙ F^s and α^t ⊙ F^t over the batch: what each branch adds to the residual stream, which the gates alone do
    not show (a branch conv can grow while its gate stays at ½).
    """

    def __init__(
        self,
        channels: int,
        time_emb_dim: int,
        kernel_t: int = 3,
        noise_std: float = 0.5,
        groups: int = 8,
        hidden: int | None = None,
        fusion: Fusion = "gating",
    ):
        super().__init__()
        if fusion not in FUSIONS:
            raise ValueError(f"MoSTBlock: fusion must be one of {', '.join(FUSIONS)}, got {fusion!r}")
        self.fusion = fusion
        if kernel_t < 1 or kernel_t % 2 == 0:
            raise ValueError(f"MoSTBlock: kernel_t must be a positive odd number, got {kernel_t}")
        if noise_std < 0:
            raise ValueError(f"MoSTBlock: noise_std must be >= 0, got {noise_std}")
        self.kernel_t = kernel_t
        self.noise_std = float(noise_std)
        self.norm = group_norm(channels, groups)
        self.spatial = RingConv2d(channels, channels, 3)
        self.temporal = nn.Conv2d(kernel_t * channels, channels, 1)  # see temporal_conv for the layout
        zeroed: list[nn.Module] = [self.spatial, self.temporal]  # the block starts as the identity
        if fusion == "gating":
            hidden = hidden or max(channels, 16)
            self.gate = nn.Sequential(nn.Linear(channels + time_emb_dim, hidden), nn.SiLU(), nn.Linear(hidden, 2))
            zeroed.append(self.gate[-1])  # gates start at (½, ½)
        elif fusion == "cascade":
            self.norm_t = group_norm(channels, groups)  # the temporal branch reads the spatial branch's output
        elif fusion == "concat":
            self.fuse = nn.Conv2d(2 * channels, channels, 1)
            zeroed = [self.fuse]  # zero branches behind a zero fuse would get no gradient: only the fuse starts at 0
        for layer in zeroed:
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)
        self.last_gates: Tensor | None = None
        self.last_cv: Tensor | None = None
        self.record_updates = False
        self.last_updates: Tensor | None = None

    def gates(self, x: Tensor, emb: Tensor, frames: int, generator: torch.Generator | None = None) -> Tensor:
        """(α^s, α^t) per sequence: x (B·L, C, H, W), emb (B·L, E) -> (B, 2), rows sum to 1."""
        batch = x.shape[0] // frames
        pooled = x.unflatten(0, (batch, frames)).mean(dim=(1, 3, 4))  # (B, C)
        time = emb.unflatten(0, (batch, frames)).mean(dim=1)  # (B, E); equal over L within a sequence
        logits = self.gate(torch.cat([pooled, time], dim=1)).float()  # (B, 2)
        if self.training and self.noise_std > 0:
            # drawn on the CPU (or the generator's device) and moved: a checkpointed CPU RNG state resumes it exactly
            device = generator.device if generator is not None else torch.device("cpu")
            noise = torch.randn(logits.shape, generator=generator, device=device).to(logits.device)
            logits = logits + self.noise_std * noise
        return torch.softmax(logits, dim=1)

    def forward(self, x: Tensor, emb: Tensor, frames: int, generator: torch.Generator | None = None) -> Tensor:
        """x (B·L, C, H, W), emb (B·L, E) SiLU-activated, frames = L -> (B·L, C, H, W)."""
        if frames < 1 or x.shape[0] % frames:
            raise ValueError(f"MoSTBlock: batch {x.shape[0]} is not a whole number of {frames}-frame sequences")
        h = F.silu(self.norm(x))
        f_s = self.spatial(h)  # (B·L, C, H, W) intra-frame
        if self.fusion == "cascade":
            x_s = x + f_s
            h_t = F.silu(self.norm_t(x_s))
            return x_s + temporal_conv(h_t, self.temporal.weight, self.temporal.bias, frames)
        f_t = temporal_conv(h, self.temporal.weight, self.temporal.bias, frames)  # (B·L, C, H, W) across frames
        if self.fusion == "add":
            return x + f_s + f_t
        if self.fusion == "concat":
            return x + self.fuse(torch.cat([f_s, f_t], dim=1))
        gates = self.gates(x, emb, frames, generator)  # (B, 2)
        alpha = gates.to(x.dtype).repeat_interleave(frames, dim=0)[:, :, None, None, None]  # (B·L, 2, 1, 1, 1)
        self.last_gates = gates.detach()
        self.last_cv = cv_squared(gates.sum(dim=0))  # importance = batch sum of each branch's gate
        update_s, update_t = alpha[:, 0] * f_s, alpha[:, 1] * f_t
        if self.record_updates:
            rms = [v.detach().float().square().mean().sqrt() for v in (x, update_s, update_t)]
            self.last_updates = torch.stack(rms)
        return x + update_s + update_t
