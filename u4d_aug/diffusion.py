"""Continuous-time Gaussian diffusion: cosine log-SNR schedule and the training losses of the U4D stages.

Schedule choice: continuous time, t ~ U(0, 1), cosine log-SNR as R2DM
`models/diffusion/continuous_time.py` (generation_protocols.md §2.2):
    logSNR(t) = -2 log tan(t_min + t (t_max - t_min)), t_min = atan(e^-7.5), t_max = atan(e^7.5) (+15 .. -15)
    alpha = sqrt(sigmoid(logSNR)),  sigma = sqrt(sigmoid(-logSNR)),  x_t = alpha x0 + sigma eps.
Why continuous rather than a discrete T-step table: the network is conditioned on log-SNR, which is defined
for every t in [0, 1], so one trained model serves any sampler and any step count (256-step ancestral DDPM,
32-step DDIM, ...) without retraining or re-spacing a table; the cosine shape spends its steps near the
middle of the SNR range where the ε-loss is informative, and ±15 keeps alpha, sigma away from 0 in float32.

The trained module's forward returns the loss (DESIGN §4.1, R2DM `GaussianDiffusion.forward`); the network
only sees (x_t, log-SNR, condition), never the schedule (DESIGN §4.2); samplers live in `u4d_aug.sampling`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from u4d_aug.errors import InputError

LOG_SNR_MAX = 15.0  # logSNR(t=0)
LOG_SNR_MIN = -15.0  # logSNR(t=1)
_T_MIN = math.atan(math.exp(-0.5 * LOG_SNR_MAX))
_T_MAX = math.atan(math.exp(-0.5 * LOG_SNR_MIN))


def log_snr(t: Tensor) -> Tensor:
    """Cosine log-SNR of continuous time t in [0, 1]: +15 at t=0 down to -15 at t=1 (R2DM / VDM)."""
    return -2.0 * torch.log(torch.tan(_T_MIN + t * (_T_MAX - _T_MIN)))


def alpha_sigma(log_snr: Tensor) -> tuple[Tensor, Tensor]:
    """(alpha, sigma) = (sqrt(sigmoid(logSNR)), sqrt(sigmoid(-logSNR))); alpha² + sigma² = 1 (R2DM, VP)."""
    return torch.sigmoid(log_snr).sqrt(), torch.sigmoid(-log_snr).sqrt()


def min_snr_weight(log_snr: Tensor, gamma: float | None) -> Tensor:
    """Min-SNR-γ weight of the ε-loss: min(SNR, γ) / SNR (Hang et al. 2023; R2DM: γ = 5); 1 if γ is None."""
    if gamma is None:
        return torch.ones_like(log_snr)
    return torch.clamp(gamma * torch.exp(-log_snr), max=1.0)


@dataclass
class DiffusionConfig:
    """Diffusion stage and loss terms (paper §2: L_u for stage 1, L_c for stage 2; R2DM for the baseline)."""

    # stage1 / stage2: one U4D stage per net; u4d: one net for both stages (the paper's unified latent
    # representation), told apart by a task embedding, both tasks in every batch; baseline: R2DM's single stage;
    # detail: a cascade's second net, which completes a full-width scan given every s-th column (`u4d_aug.cascade`),
    # conditioned as stage 2 is
    stage: Literal["stage1", "stage2", "baseline", "u4d", "detail"] = "baseline"
    # what the net predicts: eps (ε, R2DM) or v = α ε − σ x0 (Salimans & Ho 2022); samplers read ε̂ either way
    parameterization: Literal["eps", "v"] = "eps"
    min_snr_gamma: float | None = 5.0  # None turns Min-SNR weighting off
    mask_weight: float = 1.0  # λ of L_u = ε-MSE + λ · BCE(m_u, m_p) (stage 1 only)
    mask_pos_weight: float = 1.0  # BCE weight of positive (uncertain) pixels; m_u is sparse
    most_cv_weight: float = 0.01  # weight of Σ CV² of the MoST gate importances (nets with net.most only)
    # stage 2: in training, the uncertain region's values of the condition x0_u get Gaussian noise of a std drawn
    # per sample in [0, cond_noise], so stage 2 learns to read an imperfect, generated P_u (conditioning
    # augmentation of cascaded diffusion models, Ho et al. 2022); 0 = the exact x0_u
    cond_noise: float = 0.0
    # training draws t ~ U(0, train_t_max): 1 is the whole schedule (R2DM); below 1 a fine-tune of the low-noise end,
    # where a few-step sampler's last x̂0 is made (0.1: log-SNR >= 3.7)
    train_t_max: float = 1.0
    # input perturbation (DDPM-IP, Ning et al. 2023): the net sees x_t = α x0 + σ (ε + γ ξ) and still predicts ε, so
    # it learns to remove a little more noise than the level it is told, the error a sampler's earlier x̂0 leaves
    # (exposure bias); γ = 0 is the plain loss
    input_perturbation: float = 0.0
    # stage u4d: the share of each batch's samples that train the stage-1 task (the first round(share · B) of the
    # batch; the rest train stage 2), so every batch trains both tasks
    stage1_share: float = 0.5

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise InputError(f"diffusion.stage must be one of {', '.join(map(repr, STAGES))}, got {self.stage!r}")
        if self.parameterization not in ("eps", "v"):
            raise InputError(f"diffusion.parameterization must be 'eps' or 'v', got {self.parameterization!r}")
        if not 0.0 < self.stage1_share < 1.0:
            raise InputError(f"diffusion.stage1_share must be in (0, 1), got {self.stage1_share}")
        if self.min_snr_gamma is not None and self.min_snr_gamma <= 0:
            raise InputError(f"diffusion.min_snr_gamma must be > 0 or null, got {self.min_snr_gamma}")
        if self.mask_weight < 0 or self.mask_pos_weight <= 0:
            raise InputError("diffusion.mask_weight must be >= 0 and diffusion.mask_pos_weight > 0")
        if self.most_cv_weight < 0:
            raise InputError(f"diffusion.most_cv_weight must be >= 0, got {self.most_cv_weight}")
        if self.cond_noise < 0 or (self.cond_noise > 0 and self.stage not in CONDITIONED):
            raise InputError(
                f"diffusion.cond_noise must be >= 0, and 0 unless stage=stage2, u4d or detail, got {self.cond_noise}"
            )
        if not 0.0 <= self.input_perturbation < 1.0:
            raise InputError(f"diffusion.input_perturbation must be in [0, 1), got {self.input_perturbation}")
        if not 0.0 < self.train_t_max <= 1.0:
            raise InputError(f"diffusion.train_t_max must be in (0, 1], got {self.train_t_max}")


STAGES: tuple[str, ...] = ("stage1", "stage2", "baseline", "u4d", "detail")
CONDITIONED: tuple[str, ...] = ("stage2", "u4d", "detail")  # the stages whose net reads concat(x0_u, m_u)
STAGE1_TASK, STAGE2_TASK = 0, 1  # the task ids of a u4d net's two stages (net.num_tasks = 2)


def net_heads(stage: str, image_channels: int = 2) -> tuple[bool, int, int]:
    """(mask head, condition channels, tasks) of the net a stage trains on images of `image_channels` (2: depth and
    reflectance; a latent generator's: the autoencoder's latent channels): stage 1 has the mask head, stage 2 reads
    concat(x0_u, m_u) (a detail net: the layout's columns and their mask), a u4d net has both and a task embedding
    for its two stages."""
    cond = image_channels + 1
    if stage == "u4d":
        return True, cond, 2
    return stage == "stage1", cond if stage in ("stage2", "detail") else 0, 0


def stage1_count(batch: int, share: float) -> int:
    """How many of a u4d batch's samples train stage 1: round(share · B), at least 1 and at most B − 1."""
    if batch < 2:
        raise InputError(f"stage u4d trains both stages in every batch: batch_size must be >= 2, got {batch}")
    return min(batch - 1, max(1, round(share * batch)))


def empty_condition(like: Tensor) -> Tensor:
    """The stage-1 task's condition of a u4d net for images shaped like `like` (..., C, H, W): stage 2's condition
    (..., C + 1, H, W) with no x0_u (−1) and an empty m_u (0)."""
    return torch.cat([torch.full_like(like, -1.0), torch.zeros_like(like[..., :1, :, :])], dim=-3)


def eps_from_v(x_t: Tensor, lam: Tensor, v: Tensor) -> Tensor:
    """ε̂ = σ x_t + α v̂ of a v-prediction (v = α ε − σ x0, Salimans & Ho 2022) at log-SNR lam (B,) or ()."""
    alpha, sigma = alpha_sigma(lam.reshape(-1).view(-1, *([1] * (x_t.dim() - 1))).to(x_t.dtype))
    return sigma * x_t + alpha * v


def noisy_condition(
    x0_u: Tensor, m_u: Tensor, max_std: float, generator: torch.Generator | None, clamp: bool = True
) -> Tensor:
    """x0_u (B, [L,] C, H, W) with N(0, s²) added inside m_u (B, [L,] 1, H, W), s ~ U(0, max_std) per sample, clamped
    to [-1, 1] (`clamp`; a latent's values are unbounded); pixels outside the mask stay as they are (−1 in a range
    image). Conditioning augmentation (Ho et al. 2022, §4.2)."""
    batch = x0_u.shape[0]
    draw_device = generator.device if generator is not None else x0_u.device
    std = torch.rand(batch, generator=generator, device=draw_device).to(x0_u.device, x0_u.dtype) * max_std
    noise = torch.randn(x0_u.shape, generator=generator, device=draw_device).to(x0_u.device, x0_u.dtype)
    noisy = x0_u + std.view(batch, *([1] * (x0_u.dim() - 1))) * noise
    noisy = noisy.clamp(-1.0, 1.0) if clamp else noisy
    return torch.where(m_u.bool().expand_as(x0_u), noisy, x0_u)


def stage_cond(x0_u: Tensor, m_u: Tensor) -> Tensor:
    """Stage-2 condition channels concat(x0_u, m_u): (..., 2, H, W) + (..., 1, H, W) -> (..., 3, H, W)."""
    return torch.cat([x0_u, m_u.to(x0_u.dtype)], dim=-3)


class GaussianDiffusion(nn.Module):
    """Wraps ε_θ; forward returns the stage's training losses from clean data (R2DM `GaussianDiffusion`)."""

    def __init__(self, net: nn.Module, cfg: DiffusionConfig, latent: bool = False):
        super().__init__()
        self.net = net
        self.cfg = cfg
        self.latent = latent  # x0 and the condition are an autoencoder's latents: the condition noise is not clamped
        net_cfg = getattr(net, "cfg", None)
        self.most = bool(getattr(net_cfg, "most", False))  # the net has MoST blocks: gate noise and the CV term
        if net_cfg is not None:  # catch a net built for another stage before the first step, not at step 1
            want_mask, want_cond, want_tasks = net_heads(cfg.stage, net_cfg.in_channels)
            if bool(net_cfg.mask_head) != want_mask:
                raise InputError(f"diffusion.stage={cfg.stage} needs net.mask_head={str(want_mask).lower()}")
            if net_cfg.cond_channels != want_cond:
                raise InputError(
                    f"diffusion.stage={cfg.stage} needs net.cond_channels={want_cond} "
                    f"(stage 2 reads x0_u and m_u), got {net_cfg.cond_channels}"
                )
            if getattr(net_cfg, "num_tasks", 0) != want_tasks:
                raise InputError(f"diffusion.stage={cfg.stage} needs net.num_tasks={want_tasks}")

    def forward(
        self,
        x0: Tensor,
        cond: Tensor | None = None,
        m_u: Tensor | None = None,
        generator: torch.Generator | None = None,
        crop_offsets: Tensor | None = None,
        poses: Tensor | None = None,
        loss_weight: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Losses for clean x0 (B, [L,] 2, H, W) in [-1, 1].

        crop_offsets (B,): the inputs are azimuth crops starting at these panorama columns (`RangeUNet.forward`).
        poses (B, [L,] P): each frame's ego motion, for nets with net.pose_dim = P > 0.
        loss_weight (W,): per-column weight of the losses (0 on the columns of a crop's margin), None = all 1.
        stage1: x0 is x0_u, m_u (B, [L,] 1, H, W) is the BCE target; the net sees only x_t.
        stage2: x0 is the full scan, cond is x0_u and m_u its mask; the net sees concat(x_t, x0_u, m_u).
        detail: as stage2, with cond the layout scan's columns and m_u their mask (`u4d_aug.cascade`).
        u4d: x0 is the full scan, cond x0_u, m_u its mask; the first `stage1_count` samples train stage 1 (target
        x0_u, an empty condition, task 0, the BCE), the others stage 2 (target x0 given x0_u, m_u, task 1).
        baseline: x0 is the full scan, no condition.
        Returns {"loss": total (with grad), "eps_mse": weighted ε (or v) term, "mask_bce": BCE (stage 1, u4d),
        "most_cv": Σ CV² of the MoST gate importances (nets with MoST; weighted by most_cv_weight in "loss")};
        u4d also logs "eps_mse_stage1" and "eps_mse_stage2".
        t, ε and the MoST gate noise are drawn from `generator` (torch's default generator if None).
        """
        stage = self.cfg.stage
        net_cond, bce_target = _stage_inputs(stage, cond, m_u)
        task, ones, rest = None, slice(None), slice(None)  # u4d: the samples of the stage-1 and stage-2 tasks
        if stage == "u4d":  # stage-1 samples first: their target is x0_u, their condition empty
            x0, task, ones, rest = _split_tasks(x0, cond, self.cfg.stage1_share)
            bce_target = m_u[ones]
        lam, alpha, sigma, eps, x_t = _diffuse(x0, self.cfg.train_t_max, generator)
        if stage in CONDITIONED and self.cfg.cond_noise > 0:  # drawn after t and ε: runs without it unchanged
            noisy = noisy_condition(cond, m_u, self.cfg.cond_noise, generator, clamp=not self.latent)
            net_cond = stage_cond(noisy, m_u)
        if stage == "u4d":
            net_cond = torch.cat([empty_condition(x0[ones]), net_cond[rest]])
        if self.cfg.input_perturbation > 0:  # drawn last: runs without it draw exactly what they drew before
            x_t = x_t + sigma * self.cfg.input_perturbation * _randn_like(x_t, generator)
        kwargs = _net_kwargs(crop_offsets, poses, task, self.most, generator)
        pred, mask_logits = self.net(x_t, lam, net_cond, **kwargs)
        if self.cfg.parameterization == "v":
            target = alpha * eps - sigma * x0
            weight = min_snr_weight(lam, self.cfg.min_snr_gamma) * torch.exp(lam) / (torch.exp(lam) + 1.0)
        else:
            target, weight = eps, min_snr_weight(lam, self.cfg.min_snr_gamma)
        weighted_mse = weight * _mean_per_sample((pred.float() - target.float()).square(), loss_weight)  # (B,)
        loss = weighted_mse.mean()
        losses = {"eps_mse": loss}
        if stage == "u4d":
            losses["eps_mse_stage1"] = weighted_mse[ones].mean()
            losses["eps_mse_stage2"] = weighted_mse[rest].mean()
        if bce_target is not None:
            losses["mask_bce"] = self._mask_bce(mask_logits, bce_target, ones, loss_weight, x0.device)
            loss = loss + self.cfg.mask_weight * losses["mask_bce"]
        if self.most:
            losses["most_cv"] = self.net.most_aux_loss()  # Shazeer et al. (2017) importance loss, over MoST blocks
            loss = loss + self.cfg.most_cv_weight * losses["most_cv"]
        losses = {k: v.detach() for k, v in losses.items()}
        losses["loss"] = loss
        return losses

    def _mask_bce(
        self, mask_logits: Tensor | None, target: Tensor, ones: slice, loss_weight: Tensor | None, device: torch.device
    ) -> Tensor:
        """Weighted BCE of the mask head's logits of the stage-1 samples against m_u (L_u's second term)."""
        if mask_logits is None:
            raise ValueError(f"GaussianDiffusion({self.cfg.stage}): the net has no mask head")
        bce = F.binary_cross_entropy_with_logits(
            mask_logits[ones].float(),
            target.to(mask_logits.device, torch.float32),
            pos_weight=torch.tensor(self.cfg.mask_pos_weight, device=device),
            reduction="none",
        )
        return _mean_per_sample(bce, loss_weight).mean()


def _stage_inputs(stage: str, cond: Tensor | None, m_u: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
    """(the net's condition concat(x0_u, m_u) or None, the BCE target m_u or None) of a stage's inputs, checked."""
    if stage in CONDITIONED:
        if cond is None or m_u is None:
            raise ValueError(f"GaussianDiffusion({stage}): needs cond=x0_u and m_u")
        return stage_cond(cond, m_u), None
    if stage == "stage1":
        if m_u is None:
            raise ValueError("GaussianDiffusion(stage1): needs m_u, the target of the mask head")
        if cond is not None:
            raise ValueError("GaussianDiffusion(stage1): stage 1 is unconditional, got cond")
        return None, m_u
    if cond is not None or m_u is not None:
        raise ValueError("GaussianDiffusion(baseline): the baseline is unconditional, got cond/m_u")
    return None, None


def _split_tasks(x0: Tensor, x0_u: Tensor, share: float) -> tuple[Tensor, Tensor, slice, slice]:
    """A u4d batch: the targets (x0_u for the first `stage1_count` samples, x0 for the rest), their task ids (B,) and
    the slices of the stage-1 and stage-2 samples."""
    batch = x0.shape[0]
    first = stage1_count(batch, share)
    ones, rest = slice(0, first), slice(first, None)
    target = torch.cat([x0_u[ones], x0[rest]])
    task = torch.cat([torch.full((first,), STAGE1_TASK), torch.full((batch - first,), STAGE2_TASK)])
    return target, task.to(target.device), ones, rest


def _diffuse(
    x0: Tensor, t_max: float, generator: torch.Generator | None
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """t ~ U(0, t_max) (B,) then ε, both from `generator`: (log-SNR (B,), alpha, sigma, ε, x_t = alpha x0 + sigma ε)."""
    batch = x0.shape[0]
    draw_device = generator.device if generator is not None else x0.device
    t = torch.rand(batch, generator=generator, device=draw_device).to(x0.device) * t_max  # (B,)
    eps = torch.randn(x0.shape, generator=generator, device=draw_device).to(x0.device, x0.dtype)
    lam = log_snr(t)  # (B,)
    alpha, sigma = alpha_sigma(lam.view(batch, *([1] * (x0.dim() - 1))))
    return lam, alpha, sigma, eps, alpha * x0 + sigma * eps


def _randn_like(x: Tensor, generator: torch.Generator | None) -> Tensor:
    """Standard normal noise of x's shape drawn from `generator` (on its device), moved to x's device and dtype."""
    draw_device = generator.device if generator is not None else x.device
    return torch.randn(x.shape, generator=generator, device=draw_device).to(x.device, x.dtype)


def _net_kwargs(
    crop_offsets: Tensor | None,
    poses: Tensor | None,
    task: Tensor | None,
    most: bool,
    generator: torch.Generator | None,
) -> dict:
    """The optional inputs of the net's forward that are set: crop offsets, poses, task ids, the generator of the
    MoST gate noise (nets with MoST only)."""
    kwargs = {}
    if crop_offsets is not None:
        kwargs["crop_offsets"] = crop_offsets
    if poses is not None:
        kwargs["poses"] = poses
    if task is not None:
        kwargs["task"] = task
    if most:
        kwargs["generator"] = generator
    return kwargs


def _mean_per_sample(values: Tensor, column_weight: Tensor | None) -> Tensor:
    """(B, ...) -> (B,) mean over everything but the batch; with a (W,) column weight, its weighted mean."""
    if column_weight is None:
        return values.flatten(1).mean(dim=1)
    weight = column_weight.to(values.device, values.dtype).expand_as(values)
    return (values * weight).flatten(1).sum(dim=1) / weight.flatten(1).sum(dim=1).clamp(min=1e-12)
