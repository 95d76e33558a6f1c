"""Helpers shared by tests: a benchmark script as a module, a tiny diffusion checkpoint as train-diffusion writes it."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

from u4d_aug.config import load_config
from u4d_aug.ema import EMA
from u4d_aug.io import atomic_torch_save
from u4d_aug.train import DiffusionTrainConfig, build_net, checkpoint_state

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "configs" / "u4d" / "tiny.yaml"
TINY_MOST = REPO / "configs" / "u4d" / "tiny_most.yaml"


def load_script(name: str) -> ModuleType:
    """benchmarks/NAME.py as a module (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def save_checkpoint(
    path: Path, preset: Path = TINY, overrides: tuple[str, ...] = (), step: int = 0, edit: Callable | None = None
) -> Path:
    """An (untrained) checkpoint of `preset` + overrides; `edit(net)` may change the weights before the EMA copy."""
    cfg = load_config(DiffusionTrainConfig, preset, list(overrides))
    net = build_net(cfg)
    if edit is not None:
        edit(net)
    atomic_torch_save(path, checkpoint_state(cfg, step, net, EMA(net)))
    return path
