"""The optimiser of a seg-train run and its learning rate: AdamW with weight decay on weights only (nanoGPT), linear
warm-up then cosine decay per step, optionally annealed to the wall-clock budget (optim.anneal_to "budget")."""

from __future__ import annotations

import math

import torch
from torch import nn

from segmentation.config import SegOptimConfig


def learning_rate(step: int, cfg: SegOptimConfig, time_fraction: float = 0.0) -> float:
    """Linear warm-up over warmup_steps, then cosine from lr down to min_lr_ratio * lr (nanoGPT get_lr).

    time_fraction (share of the wall-clock budget used, optim.anneal_to "budget") moves the cosine on when the
    budget runs out before the steps do: progress = max(step progress, time_fraction).
    """
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    decay_steps = max(1, cfg.steps - cfg.warmup_steps)
    progress = min(1.0, max((step - cfg.warmup_steps) / decay_steps, time_fraction))
    min_lr = cfg.lr * cfg.min_lr_ratio
    return min_lr + 0.5 * (1.0 + math.cos(math.pi * progress)) * (cfg.lr - min_lr)


def make_optimizer(model: nn.Module, cfg: SegOptimConfig) -> torch.optim.AdamW:
    """AdamW with weight decay on >= 2-d weights only (convs, linears), not on biases and norms (nanoGPT)."""
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [
        {"params": [p for p in params if p.dim() >= 2], "weight_decay": cfg.weight_decay},
        {"params": [p for p in params if p.dim() < 2], "weight_decay": 0.0},
    ]
    return torch.optim.AdamW(groups, lr=cfg.lr, betas=cfg.betas)
