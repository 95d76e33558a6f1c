"""Exponential moving average of network weights for sampling (R2DM uses `ema-pytorch`, decay 0.995)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn


class EMA:
    """Shadow weights θ_ema ← decay·θ_ema + (1 − decay)·θ; buffers are copied; warm-up updates copy outright.

    `warmup_steps`: for the first that many calls to `update` the shadow is set to the weights (decay 0), as
    `ema-pytorch`'s `update_after_step`, so early random weights are not averaged in. Pass the unwrapped model
    (not the DDP wrapper) so parameter names match the checkpoint.
    """

    def __init__(self, model: nn.Module, decay: float = 0.995, warmup_steps: int = 0):
        if not 0.0 <= decay <= 1.0:
            raise ValueError(f"EMA decay must be in [0, 1], got {decay}")
        if warmup_steps < 0:
            raise ValueError(f"EMA warmup_steps must be >= 0, got {warmup_steps}")
        self.decay = float(decay)
        self.warmup_steps = int(warmup_steps)
        self.num_updates = 0
        self.params: dict[str, Tensor] = {n: p.detach().clone() for n, p in model.named_parameters()}
        self.buffers: dict[str, Tensor] = {n: b.detach().clone() for n, b in model.named_buffers()}

    def current_decay(self) -> float:
        """Decay applied by the next `update` (0 during warm-up)."""
        return 0.0 if self.num_updates < self.warmup_steps else self.decay

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the shadow towards `model`'s current weights."""
        decay = self.current_decay()
        for name, param in model.named_parameters():
            shadow = self.params[name]
            if shadow.is_floating_point():
                shadow.lerp_(param.detach().to(shadow.dtype), 1.0 - decay)
            else:
                shadow.copy_(param.detach())
        for name, buffer in model.named_buffers():
            self.buffers[name].copy_(buffer.detach())
        self.num_updates += 1

    @torch.no_grad()
    def copy_to(self, model: nn.Module) -> None:
        """Write the shadow weights into `model` (e.g. a separate sampling copy of the net)."""
        for name, param in model.named_parameters():
            param.copy_(self.params[name])
        for name, buffer in model.named_buffers():
            buffer.copy_(self.buffers[name])

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: decay, warm-up, update count, shadow parameters and buffers."""
        return {
            "decay": self.decay,
            "warmup_steps": self.warmup_steps,
            "num_updates": self.num_updates,
            "params": {k: v.clone() for k, v in self.params.items()},
            "buffers": {k: v.clone() for k, v in self.buffers.items()},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from `state_dict()`; the parameter names must match the model this EMA was built for."""
        for key, own in (("params", self.params), ("buffers", self.buffers)):
            missing = sorted(set(own) - set(state[key]))
            unexpected = sorted(set(state[key]) - set(own))
            if missing or unexpected:
                raise ValueError(f"EMA state {key} do not match the model: missing {missing}, unexpected {unexpected}")
            for name, value in state[key].items():
                own[name].copy_(value)
        self.decay = float(state["decay"])
        self.warmup_steps = int(state["warmup_steps"])
        self.num_updates = int(state["num_updates"])
