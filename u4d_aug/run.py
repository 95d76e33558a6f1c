"""The run layer under every training loop: output folder, resolved config, jsonl log, checkpoints, clock, host.

A loop (`u4d_aug.train`, `segmentation.train`) stands on it as nanoGPT's train.py stands on its globals, under the
run lock of OUT (`u4d_aug.runlock`): `open_run` finds where the run starts (`u4d_aug.runfolder`: step 0, or the
checkpoint it resumes from, loaded weights-only and checked to be a training checkpoint of the loop's kind);
`begin_run` (rank 0) saves the resolved config as OUT/config.yaml, rewinds OUT/log.jsonl to the resumed step and
appends the machine to OUT/hosts.jsonl; `restore` loads a checkpoint's states (warning when the config changed);
`save_checkpoint` writes one atomically and keeps the newest, `newest_checkpoint` finds it in a run folder; the
`Clock` counts wall-clock seconds across resumes against the budget. Seeds of what a step draws
come from `u4d_aug.seeding.derived_seed(seed, stream, step, rank)`, so a resumed run draws what an uninterrupted one
would.

Checkpoints are one format: {kind, config, step, elapsed, model, optimizer, ema, rng: {torch, seed}, ...}
(`checkpoint_state`), `kind` naming the writer ("u4d-diffusion", "u4d-seg-checkpoint"). seg-train checkpoints
written before this layer name their kind under "format" instead; `checkpoint_kind` reads both.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
import warnings
from pathlib import Path
from typing import Any

import torch

from u4d_aug.config import config_to_dict, save_config, without_removed_keys
from u4d_aug.distributed import DistInfo, budget_fraction, budget_used
from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import append_jsonl, atomic_torch_save, atomic_write_text, load_checkpoint, read_jsonl
from u4d_aug.runfolder import CHECKPOINT_GLOB, checkpoints, prepare, resume_point
from u4d_aug.validate import check_state_fits

logger = logging.getLogger(__name__)

LOG_NAME, HOSTS_NAME, CONFIG_NAME = "log.jsonl", "hosts.jsonl", "config.yaml"
# kinds that checkpoints written before the run layer carry under "format" (seg-train's) instead of "kind"
KINDS_UNDER_FORMAT = ("u4d-seg-checkpoint",)


def checkpoint_kind(state: dict) -> str | None:
    """The writer a checkpoint names: its "kind", or the "format" of a seg-train checkpoint older than the field."""
    kind = state.get("kind")
    if kind is None and state.get("format") in KINDS_UNDER_FORMAT:
        kind = state["format"]
    return kind


def checkpoint_state(
    kind: str, cfg: Any, step: int, elapsed: float, model: Any, optimizer: Any = None, ema: Any = None, **extra: Any
) -> dict:
    """What a training checkpoint holds: kind, resolved config, step, wall-clock seconds, the state dicts of model,
    optimizer and EMA / teacher (None when absent), the global torch RNG and the run's seed, then `extra`."""
    return {
        "kind": kind,
        "config": config_to_dict(cfg),
        "step": step,
        "elapsed": elapsed,
        "model": model.state_dict(),
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "ema": None if ema is None else ema.state_dict(),
        "rng": {"torch": torch.get_rng_state(), "seed": cfg.seed},
        **extra,
    }


@dataclasses.dataclass
class Start:
    """Where a run starts: step 0 (no checkpoint), or the loaded checkpoint at `path` it resumes from."""

    path: Path | None = None
    checkpoint: dict | None = None

    @property
    def step(self) -> int:
        return 0 if self.checkpoint is None else int(self.checkpoint["step"])

    @property
    def elapsed(self) -> float:
        """Wall-clock seconds of the starts before this one."""
        return 0.0 if self.checkpoint is None else float(self.checkpoint.get("elapsed", 0.0))


def open_run(out: Path, resume: str | Path | None, is_main: bool, kind: str, command: str) -> Start:
    """Where the run in OUT starts (`u4d_aug.runfolder.resume_point`), its checkpoint loaded and checked: written by
    `command` (its `kind`) with the optimizer state a resume needs. Rank 0 first removes temp files of killed writes
    and the log of a run killed before its first checkpoint (`u4d_aug.runfolder.prepare`)."""
    path = resume_point(out, resume)
    if is_main:
        prepare(out, path, LOG_NAME)
    if path is None:
        return Start()
    ckpt = load_checkpoint(path, f"{command} checkpoint to resume from")
    found = checkpoint_kind(ckpt)
    if found != kind:
        what = f"a {found} checkpoint" if isinstance(found, str) else "another kind of file"
        raise InputError(f"{path}: not a {command} checkpoint ({what}); resume from OUT/checkpoints/{CHECKPOINT_GLOB}")
    if ckpt.get("optimizer") is None or "rng" not in ckpt:
        raise InputError(
            f"{path}: holds weights only (exported weights or a final model.pt), no optimizer or EMA state; resume "
            f"from OUT/checkpoints/{CHECKPOINT_GLOB}"
        )
    return Start(path, ckpt)


def restore(
    start: Start,
    cfg: Any,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    ema: Any = None,
    ignore: tuple[str, ...] = (),
) -> None:
    """Resuming (nothing at step 0): warn about config changes (`warn_config_changes`, `ignore`d keys apart), then
    load the checkpoint's model, optimizer and (given) EMA / teacher states, and the global torch RNG."""
    ckpt = start.checkpoint
    if ckpt is None:
        return
    changed = warn_config_changes(start, cfg, ignore)
    hint = f"the config changed: {'; '.join(changed)}" if changed else ""
    check_state_fits(ckpt.get("model"), model.state_dict(), f"{start.path} (model)", hint)
    model.load_state_dict(ckpt["model"])
    try:
        optimizer.load_state_dict(ckpt["optimizer"])
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise InputError(f"{start.path}: its 'optimizer' state does not fit this run's optimizer ({exc})") from None
    if ema is not None:
        if ckpt.get("ema") is None:
            raise InputError(f"{start.path}: has no EMA / teacher weights (its run had none, e.g. mode 'supervised')")
        ema.load_state_dict(ckpt["ema"])
    torch.set_rng_state(ckpt["rng"]["torch"])


def warn_config_changes(start: Start, cfg: Any, ignore: tuple[str, ...] = ()) -> list[str]:
    """Resuming with another config is allowed (e.g. more steps) but not exact: warn which keys differ, and return
    them ("key: old -> new"). A key the checkpoint predates, at its default value, is no change; nor is a
    since-removed key at its "off" value."""
    old, removed = without_removed_keys(type(cfg), start.checkpoint.get("config") or {})
    defaults = {key: value for key, _, value in _differences({}, config_to_dict(type(cfg)()))}
    changed = [
        f"{key}: {a!r} -> {b!r}"
        for key, a, b in _differences(old, config_to_dict(cfg))
        if key not in ignore and not (a is _ABSENT and defaults.get(key, _ABSENT) == b)
    ]
    changed += [f"{key}: {value!r} -> (removed)" for key, value in removed.items()]
    if changed:
        warnings.warn(f"{start.path}: resuming with a changed config ({'; '.join(changed)})", stacklevel=2)
    return changed


def begin_run(out: Path, cfg: Any, start: Start, info: DistInfo) -> None:
    """Rank 0: OUT/config.yaml (the resolved config), OUT/log.jsonl rewound to the resumed step (its later records
    are written again), and this start's machine appended to OUT/hosts.jsonl (wall-clock figures read with it)."""
    if not info.is_main:
        return
    log = out / LOG_NAME
    if start.checkpoint is not None:
        logger.info("resuming from %s at step %d", start.path, start.step)
        if log.is_file():
            kept = [record for record in read_jsonl(log) if record.get("step", 0) <= start.step]
            atomic_write_text(log, "".join(json.dumps(record) + "\n" for record in kept))
    save_config(cfg, out / CONFIG_NAME)
    append_jsonl(out / HOSTS_NAME, {"step": start.step, "world_size": info.world_size, **host_info()})


def newest_checkpoint(out: Path) -> Path:
    """OUT/checkpoints/step_*.pt of the highest step (a run folder given where a checkpoint is read)."""
    found = checkpoints(out)
    if not found:
        raise InputError(f"{Path(out) / 'checkpoints'}: no {CHECKPOINT_GLOB} checkpoint in this run folder")
    return found[-1]


def save_checkpoint(out: Path, state: dict, keep: int) -> Path:
    """Write OUT/checkpoints/step_XXXXXXX.pt of state["step"] atomically, then delete all but the newest `keep`
    (0 = keep all)."""
    path = out / "checkpoints" / f"step_{int(state['step']):07d}.pt"
    atomic_torch_save(path, state)
    if keep > 0:
        for old in sorted(path.parent.glob(CHECKPOINT_GLOB))[:-keep]:
            old.unlink(missing_ok=True)
    return path


@dataclasses.dataclass
class Clock:
    """Wall-clock seconds of a run across its starts (`before`: those of the earlier ones) against its budget of
    `max_minutes` (0 = none); rank 0's reading decides for every rank, so all stop at the same step."""

    max_minutes: float
    before: float = 0.0
    t0: float = dataclasses.field(default_factory=time.perf_counter)

    def elapsed(self) -> float:
        return self.before + time.perf_counter() - self.t0

    def fraction(self) -> float:
        """Share of the budget used so far, in [0, 1] (a collective)."""
        return budget_fraction(self.elapsed(), self.max_minutes)

    def read(self) -> tuple[float, bool]:
        """(seconds so far, whether they used the budget) (a collective)."""
        elapsed = self.elapsed()
        return elapsed, budget_used(elapsed, self.max_minutes)


class _Absent:
    def __repr__(self) -> str:
        return "(absent)"


_ABSENT = _Absent()  # a key one config has and the other lacks


def _differences(old: dict, new: dict, prefix: str = "") -> list[tuple[str, object, object]]:
    """(dotted key, old value, new value) of every leaf that differs; _ABSENT where a side lacks the key."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, _ABSENT), new.get(key, _ABSENT)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif isinstance(b, dict) and a is _ABSENT:
            out += _differences({}, b, f"{prefix}{key}.")
        elif a != b:
            out.append((f"{prefix}{key}", a, b))
    return out
