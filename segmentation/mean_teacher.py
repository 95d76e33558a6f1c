"""Mean teacher for LaserMix (Tarvainen & Valpola 2017; LaserMix `semi_base.py` + mmdet `MeanTeacherHook`).

BatchNorm policy (`MeanTeacherConfig.bn_mode`), chosen explicitly:

- "batch" (default, as upstream): `ema_update` averages parameters only; the teacher's forward passes use
  batch statistics (`teacher_mode` puts its BatchNorm layers in train mode), and its running statistics are
  updated by those forwards, so the teacher evaluated at the end carries statistics of its own weights
  rather than the student's. Upstream gets this by accident (mmengine calls `model.train()` every
  iteration); we do it on purpose. It is sound here because BatchNorm on voxel features normalises over
  all occupied voxels of the batch (tens of thousands even for one scan), so batch statistics are stable
  at the small batches of a CPU preset. Deviation: dropout (SPVCNN's) stays off in the teacher, so
  pseudo-labels are deterministic given the batch; upstream leaves it on.
- "copy_student": the teacher runs fully in eval mode and `ema_update` is followed by `copy_buffers`
  (BatchNorm running statistics copied from the student). Pseudo-labels then do not depend on the
  batch composition, at the price of statistics that belong to slightly different weights.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class MeanTeacherConfig:
    """Semi-supervised hyper-parameters; defaults are the LaserMix MinkUNet18 SemanticKITTI config."""

    ema_decay: float = 0.99  # teacher <- decay * teacher + (1 - decay) * student, every step (mmdet momentum 0.01)
    pseudo_threshold: float = 0.9  # teacher confidence below this -> ignore id (0.95 upstream on nuScenes)
    # class-balanced pseudo-labels (CBST, Zou et al. 2018): each predicted class keeps at least this top share of
    # its points by confidence in the batch (class threshold = min(pseudo_threshold, the confidence at that
    # share)); None = one global threshold (LaserMix). A young teacher is confident on road and vegetation only,
    # so a global 0.9 gives the rare classes no pseudo-label at all.
    pseudo_class_share: float | None = None
    # L_mt weight: 200 for MinkUNet18 / SemanticKITTI upstream (Cylinder3D: 250 SK, 500 nuScenes); large
    # because the MSE is averaged over N x C, so the right value scales with the number of classes.
    consistency_weight: float = 200.0
    # sigmoid ramp-up of the L_mt weight, w * exp(-5 (1 - t/T)^2) over the first T steps (Tarvainen & Valpola 2017;
    # Laine & Aila 2017): the young teacher is close to the random init, and matching it makes the student
    # underconfident on short schedules; 0 = constant weight (LaserMix upstream, trained for many epochs)
    consistency_rampup_steps: int = 0
    # burn-in (Unbiased Teacher, Liu et al. 2021): the first steps train the student on the labeled scans only and
    # the teacher is a copy of the student (weights and BatchNorm statistics), so the first pseudo-labels come from
    # the burnt-in student; LaserMix, pseudo-labels and L_mt start after it (the ramp-up counts from there).
    # 0 = mean teacher from step 0 (LaserMix upstream).
    burn_in_steps: int = 0
    sup_weight: float = 1.0  # weight of L_sup (labeled scans)
    mix_weight: float = 1.0  # weight of L_mix (LaserMix scans with GT / pseudo-labels)
    num_areas_choices: tuple[int, ...] = (3, 4, 5, 6)  # LaserMix MinkUNet18 config
    # (down, up) pitch range in degrees; None = the sensor's (fov_down_deg, fov_up_deg)
    pitch_range_deg: tuple[float, float] | None = None
    bn_mode: Literal["batch", "copy_student"] = "batch"


def make_teacher(student: nn.Module) -> nn.Module:
    """Teacher = a frozen deep copy of the student (the mmdet hook copies the student at iteration 0)."""
    teacher = copy.deepcopy(student)
    teacher.requires_grad_(False)
    return teacher


def teacher_mode(teacher: nn.Module, bn_mode: Literal["batch", "copy_student"] = "batch") -> nn.Module:
    """Teacher's training-time mode: eval, but BatchNorm in train mode when bn_mode == "batch"."""
    if bn_mode not in ("batch", "copy_student"):
        raise ValueError(f"bn_mode must be 'batch' or 'copy_student'; got {bn_mode!r}")
    teacher.eval()
    if bn_mode == "batch":
        for module in teacher.modules():
            if isinstance(module, nn.modules.batchnorm._BatchNorm):
                module.train()
    return teacher


@torch.no_grad()
def ema_update(teacher: nn.Module, student: nn.Module, decay: float) -> None:
    """teacher <- decay * teacher + (1 - decay) * student, parameters only (mmdet MeanTeacherHook)."""
    if not 0.0 <= decay <= 1.0:
        raise ValueError(f"ema decay must be in [0, 1]; got {decay}")
    t_params, s_params = dict(teacher.named_parameters()), dict(student.named_parameters())
    if t_params.keys() != s_params.keys():
        raise ValueError("teacher and student have different parameters")
    for name, t in t_params.items():
        # lerp is exact at both ends: weight 0 keeps t, weight 1 gives s
        t.lerp_(s_params[name].detach().to(t.dtype), 1.0 - decay)


@torch.no_grad()
def copy_buffers(teacher: nn.Module, student: nn.Module) -> None:
    """Copy every buffer (BatchNorm running mean/var, counters) from the student (bn_mode "copy_student")."""
    t_buffers, s_buffers = dict(teacher.named_buffers()), dict(student.named_buffers())
    if t_buffers.keys() != s_buffers.keys():
        raise ValueError("teacher and student have different buffers")
    for name, t in t_buffers.items():
        t.copy_(s_buffers[name])


@torch.no_grad()
def pseudo_labels(
    teacher_logits: torch.Tensor, threshold: float = 0.9, ignore_index: int = 19, class_share: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pseudo-labels (N,) = argmax softmax, ignore_index where confidence (N,) < the threshold (LaserMix).

    With class_share, the threshold of predicted class c is min(threshold, t_c), t_c the confidence of its
    ceil(class_share * n_c)-th most confident of the n_c points predicted as c: every predicted class keeps at
    least that top share (class-balanced self-training, Zou et al. 2018).
    """
    confidence, labels = F.softmax(teacher_logits.float(), dim=1).max(dim=1)  # (N,), (N,)
    if class_share is None:
        keep = confidence >= threshold
    else:
        if not 0.0 < class_share <= 1.0:
            raise ValueError(f"class_share must be in (0, 1]; got {class_share}")
        per_class = torch.full((teacher_logits.shape[1],), float(threshold), device=confidence.device)  # (K,)
        for c in labels.unique().tolist():
            scores = confidence[labels == c]  # (n_c,)
            kth = torch.topk(scores, math.ceil(class_share * scores.numel())).values[-1]
            per_class[c] = torch.minimum(per_class[c], kth)
        keep = confidence >= per_class[labels]
    return labels.masked_fill(~keep, ignore_index), confidence


def view_count_error(views: int) -> str | None:
    """Why `views` is not a valid number of test-time views (1-4, or a multiple of 4 up to 32), else None."""
    if 1 <= views <= 4 or (views % 4 == 0 and 4 < views <= 32):
        return None
    return f"views must be 1-4 (the scan and its x / y / xy mirrors) or a multiple of 4 up to 32, got {views}"


def scan_views(points: torch.Tensor, views: int) -> list[torch.Tensor]:
    """Test-time views of one (N, C >= 3) scan, point order kept: [scan, x mirrored, y mirrored, both][:views]
    for views <= 4; for views = 4 R the same four mirrors after each of R turns about z by multiples of
    90 / R degrees (views 8: 0 and 45 degrees). A turn voxelizes the scene on another grid, a mirror not."""
    error = view_count_error(views)
    if error is not None:
        raise ValueError(error)
    signs = [(1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)]
    turns = max(1, views // 4)
    out = []
    for i in range(views):
        sx, sy = signs[i % 4]
        view = points.clone()
        view[:, 0] *= sx
        view[:, 1] *= sy
        angle = (i // 4) * math.pi / (2 * turns)
        if angle:  # x' = c x - s y, y' = s x + c y
            c, s = math.cos(angle), math.sin(angle)
            view[:, 0], view[:, 1] = c * view[:, 0] - s * view[:, 1], s * view[:, 0] + c * view[:, 1]
        out.append(view)
    return out


def mean_view_probs(view_logits: list[torch.Tensor]) -> torch.Tensor:
    """Mean softmax over views, (N, K) logits each -> (N, K) float32 probabilities (test-time augmentation)."""
    return torch.stack([F.softmax(logits.float(), dim=1) for logits in view_logits]).mean(dim=0)


def consistency_loss(student_logits: torch.Tensor, teacher_logits: torch.Tensor) -> torch.Tensor:
    """L_mt = MSE(softmax(student), softmax(teacher).detach()), mean over N x C (LaserMix `loss_mse`)."""
    if student_logits.shape != teacher_logits.shape:
        raise ValueError(
            f"student and teacher logits differ in shape: {tuple(student_logits.shape)} vs "
            f"{tuple(teacher_logits.shape)}"
        )
    p_student = F.softmax(student_logits.float(), dim=1)  # (N, C)
    p_teacher = F.softmax(teacher_logits.detach().float(), dim=1)  # (N, C)
    return F.mse_loss(p_student, p_teacher)


def consistency_rampup(step: int, rampup_steps: int) -> float:
    """exp(-5 (1 - t/T)^2) for t < T, else 1 (the mean-teacher sigmoid ramp-up, Tarvainen & Valpola 2017)."""
    if rampup_steps <= 0 or step >= rampup_steps:
        return 1.0
    phase = 1.0 - max(step, 0) / rampup_steps
    return math.exp(-5.0 * phase * phase)


def total_loss(
    loss_sup: torch.Tensor,
    loss_mix: torch.Tensor,
    loss_mt: torch.Tensor | None,
    config: MeanTeacherConfig,
    step: int | None = None,
) -> torch.Tensor:
    """L = w_sup * L_sup + w_mix * L_mix + w_mt(step) * L_mt (LaserMix `SemiBase3DSegmentor.loss`, ramped w_mt)."""
    loss = config.sup_weight * loss_sup + config.mix_weight * loss_mix
    if loss_mt is not None:
        ramp = 1.0 if step is None else consistency_rampup(step, config.consistency_rampup_steps)
        loss = loss + config.consistency_weight * ramp * loss_mt
    return loss
