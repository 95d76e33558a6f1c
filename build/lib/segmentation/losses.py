"""Segmentation losses: cross-entropy with an ignore id and the Lovász-softmax (Berman et al., CVPR 2018).

The Lovász-softmax is the Lovász extension of the per-class Jaccard loss 1 - IoU_c evaluated at the per-point
errors m_i(c) = |1[y_i = c] - p_i(c)| (Berman, Rannen Triki, Blaschko 2018, Eq. 9 and Alg. 1), averaged over
the classes present in the target ("present" mode of the reference implementation).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from segmentation.config import LossConfig


def lovasz_grad(fg_sorted: torch.Tensor) -> torch.Tensor:
    """Gradient of the Lovász extension of Δ_J w.r.t. sorted errors (Berman et al. 2018, Alg. 1)."""
    # fg_sorted: (M,) float, ground-truth membership of the points in decreasing order of error
    gts = fg_sorted.sum()
    intersection = gts - fg_sorted.cumsum(0)  # |fg \ first i mispredicted|
    union = gts + (1.0 - fg_sorted).cumsum(0)  # |fg ∪ first i mispredicted|
    jaccard = 1.0 - intersection / union  # Δ_J(S_i) for i = 1..M
    if fg_sorted.numel() > 1:
        jaccard = torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]])
    return jaccard


def lovasz_softmax(probs: torch.Tensor, target: torch.Tensor, ignore_index: int | None = None) -> torch.Tensor:
    """Lovász-softmax of probs (N, K) against target (N,), mean over classes present in the target.

    Returns 0 (with a graph) when no valid point is left.
    """
    if ignore_index is not None:
        keep = target != ignore_index
        probs, target = probs[keep], target[keep]
    if target.numel() == 0:
        return probs.sum() * 0.0
    losses = []
    for c in torch.unique(target).tolist():
        fg = (target == c).to(probs.dtype)  # (M,)
        errors = (fg - probs[:, c]).abs()  # m_i(c)
        errors_sorted, order = torch.sort(errors, descending=True)
        losses.append(torch.dot(errors_sorted, lovasz_grad(fg[order])))
    return torch.stack(losses).mean()


def voxel_targets(target: torch.Tensor, inverse: torch.Tensor, num_voxels: int, ignore_index: int) -> torch.Tensor:
    """(M,) majority train id of the points (N,) in each voxel (inverse (N,) point -> voxel), ignore id dropped.

    A voxel whose points are all ignored gets the ignore id; ties go to the lower id. Training on one label per
    voxel is what torchsparse / SPVNAS pipelines do (they keep one point per voxel; the majority is steadier).
    """
    if target.shape != inverse.shape:
        raise ValueError(f"target {tuple(target.shape)} and inverse {tuple(inverse.shape)} must match")
    valid = target != ignore_index
    num_ids = int(target[valid].max()) + 1 if bool(valid.any()) else 1
    votes = torch.bincount(inverse[valid] * num_ids + target[valid], minlength=num_voxels * num_ids)
    votes = votes.view(num_voxels, num_ids)  # (M, ids)
    count, label = votes.max(dim=1)
    return label.masked_fill(count == 0, ignore_index)


def class_weights(counts: torch.Tensor, cfg: LossConfig) -> torch.Tensor | None:
    """(K,) CE class weights from the training point counts (K,) per train id, or None for "none".

    "inverse_sqrt": w_c = f_c^(-1/2) with f_c = counts_c / sum(counts) (SalsaNext, Cortinhal et al. 2020),
    scaled so that sum_c f_c w_c = 1 (a point weighs 1 on average), then capped at cfg.max_class_weight;
    classes without a training point get weight 1 (they never occur as a target).
    """
    if cfg.class_weighting == "none":
        return None
    elif cfg.class_weighting == "inverse_sqrt":
        share = counts.double() / counts.sum().clamp_min(1)
        present = share > 0
        weight = torch.ones_like(share)
        weight[present] = share[present].rsqrt()
        weight[present] /= (share[present] * weight[present]).sum()
        return weight.clamp(max=cfg.max_class_weight).float()
    raise ValueError(f"loss.class_weighting must be 'none' or 'inverse_sqrt'; got {cfg.class_weighting!r}")


def segmentation_loss(
    logits: torch.Tensor,
    target: torch.Tensor,
    cfg: LossConfig,
    ignore_index: int,
    class_weight: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """{"loss", "loss_ce", ["loss_lovasz"]} of logits (N, K) against train ids (N,), ignore id dropped.

    class_weight (K,) weights the cross-entropy per target class (weighted mean over points, as torch).
    """
    valid = target != ignore_index
    if not bool(valid.any()):
        zero = logits.sum() * 0.0  # keeps every parameter in the graph (DDP needs a gradient for each)
        out = {"loss": zero, "loss_ce": zero.detach()}
        if cfg.lovasz_weight > 0:
            out["loss_lovasz"] = zero.detach()
        return out
    weight = None if class_weight is None else class_weight.to(logits.device, torch.float32)
    loss_ce = F.cross_entropy(
        logits.float(), target, weight=weight, ignore_index=ignore_index, label_smoothing=cfg.label_smoothing
    )
    out = {"loss_ce": loss_ce}
    loss = cfg.ce_weight * loss_ce
    if cfg.lovasz_weight > 0:
        loss_lovasz = lovasz_softmax(logits.float().softmax(dim=1), target, ignore_index)
        out["loss_lovasz"] = loss_lovasz
        loss = loss + cfg.lovasz_weight * loss_lovasz
    out["loss"] = loss
    return out
