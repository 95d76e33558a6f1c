"""Checks of numbers and names a user hands us: finite config floats, plain names, finite training losses, loaded
weights that fit the net their config builds.

Each check raises an InputError (or its NonFiniteLossError) whose one line names the key, the name or the step.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

from u4d_aug.distributed import dist_initialized, ranks_where
from u4d_aug.errors import InputError

if TYPE_CHECKING:
    import torch


class NonFiniteLossError(InputError):
    """A training loss (or gradient norm) became NaN/inf: the run stops before the step, keeping its checkpoints."""


def nonfinite_keys(value: Any, prefix: str = "") -> list[str]:
    """Dotted keys of the NaN/inf floats in a config (dataclass, dict, list, tuple), depth first."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        items = [(f.name, getattr(value, f.name)) for f in dataclasses.fields(value)]
    elif isinstance(value, dict):
        items = list(value.items())
    elif isinstance(value, (list, tuple)):
        return [key for i, item in enumerate(value) for key in nonfinite_keys(item, f"{prefix.rstrip('.')}[{i}].")]
    elif isinstance(value, float) and not math.isfinite(value):
        return [prefix.rstrip(".")]
    else:
        return []
    return [key for name, item in items for key in nonfinite_keys(item, f"{prefix}{name}.")]


def check_finite_config(cfg: Any, prefix: str = "") -> None:
    """Refuse a config holding a NaN or infinite number (`optim.lr=.inf`), naming the key (under `prefix`)."""
    keys = nonfinite_keys(cfg)
    if keys:
        value = _get(cfg, keys[0])
        raise InputError(f"key '{prefix}{keys[0]}' must be a finite number, got {value}")


def check_positive(cfg: Any, *keys: str, allow_zero: bool = False, prefix: str = "") -> None:
    """Refuse a config whose dotted `keys` are not > 0 (>= 0 with allow_zero), naming the first such key."""
    for key in keys:
        value = _get(cfg, key)
        if value is not None and (value < 0 or (value == 0 and not allow_zero)):
            bound = ">= 0" if allow_zero else "> 0"
            raise InputError(f"key '{prefix}{key}' must be {bound}, got {value}")


def check_plain_name(name: str, what: str) -> str:
    """A name that becomes one folder or file name: not empty, no path separator, not '.' or '..'."""
    if not isinstance(name, str) or not name.strip() or name in (".", "..") or any(c in name for c in "/\\\0"):
        raise InputError(f"{what} {name!r} must be a plain name (no '/', '\\', '..'), as it names a folder")
    return name


def check_finite_loss(loss: torch.Tensor, step: int, grad_norm: torch.Tensor | float | None = None) -> None:
    """Stop at a NaN/inf loss or gradient norm of training step `step` (1-based), before the optimizer steps.

    Under torchrun every rank stops together: the loss check is agreed over ranks (a rank whose own loss is finite
    would otherwise wait in backward's gradient all-reduce for one that left); the gradient norm is taken after
    that all-reduce, so it is the same on every rank already."""
    value = float(loss.detach())
    bad_ranks = ranks_where(not math.isfinite(value))
    if bad_ranks:
        where = "" if bad_ranks == [0] and not dist_initialized() else f" on rank {', '.join(map(str, bad_ranks))}"
        raise NonFiniteLossError(
            f"training step {step}: the loss is {'not finite' if math.isfinite(value) else value}{where}; stopped "
            "without saving these weights (the last checkpoint stays; a lower learning rate may help)"
        )
    if grad_norm is not None and not math.isfinite(float(grad_norm)):
        raise NonFiniteLossError(
            f"training step {step}: the gradient norm is {float(grad_norm)}; stopped without saving these weights "
            "(the last checkpoint stays; a lower learning rate may help)"
        )


def _get(cfg: Any, key: str) -> Any:
    """The value under a dotted key ('optim.lr', 'betas[0]') of a dataclass or dict config."""
    value = cfg
    for part in key.split("."):
        name, _, index = part.partition("[")
        if name:
            value = value[name] if isinstance(value, dict) else getattr(value, name)
        if index:
            value = value[int(index.rstrip("]"))]
    return value


def state_mismatches(state: Any, expected: dict[str, Any]) -> list[str]:
    """What keeps `state` (name -> tensor) from loading into tensors of `expected` (name -> tensor): missing and
    unexpected names, other shapes, non-tensors; [] when it fits."""
    import torch

    if not isinstance(state, dict):
        return [f"a {type(state).__name__} where a name -> tensor mapping belongs"]
    problems = [f"{name}: missing" for name in expected if name not in state]
    problems += [f"{name}: not in this net" for name in state if name not in expected]
    for name, want in expected.items():
        have = state.get(name)
        if name not in state:
            continue
        if not isinstance(have, torch.Tensor):
            problems.append(f"{name}: a {type(have).__name__}, not a tensor")
        elif tuple(have.shape) != tuple(want.shape):
            problems.append(
                f"{name}: shape {tuple(have.shape)} here, {tuple(want.shape)} in the net this config builds"
            )
    return problems


def check_state_fits(state: Any, expected: dict[str, Any], source: str, hint: str = "") -> None:
    """Refuse weights that load safely but do not fit the net built from the config: one line naming the file, the
    first differing tensors and `hint` (e.g. which config keys changed) instead of torch's size-mismatch traceback."""
    problems = state_mismatches(state, expected)
    if problems:
        shown = "; ".join(problems[:3]) + (f"; and {len(problems) - 3} more" if len(problems) > 3 else "")
        raise InputError(f"{source}: its weights do not fit the net ({shown}){'; ' + hint if hint else ''}")
