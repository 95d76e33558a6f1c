"""Helpers shared by tests: the tiny presets, their configs, tiny checkpoints as train-diffusion writes them,
a benchmark script as a module, a two-process torchrun."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import torch

from u4d_aug.config import load_config
from u4d_aug.distributed import DistInfo
from u4d_aug.ema import EMA
from u4d_aug.generate import GenerateConfig
from u4d_aug.io import atomic_torch_save
from u4d_aug.metrics.extractors import ExtractorConfig
from u4d_aug.sampling_settings import SamplingSettings
from u4d_aug.stage import DiffusionTrainConfig, build_net, checkpoint_state
from u4d_aug.train import split_stage_override

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "configs" / "u4d" / "tiny.yaml"
TINY_MOST = REPO / "configs" / "u4d" / "tiny_most.yaml"
SEG_TINY = REPO / "configs" / "seg" / "tiny.yaml"
SEG_TINY_SEMI = REPO / "configs" / "seg" / "tiny_semi.yaml"
EXTRACTOR_TINY = REPO / "configs" / "extractor" / "tiny.yaml"
CPU = DistInfo(0, 1, 0, torch.device("cpu"))  # a single process on the CPU


def load_script(name: str) -> ModuleType:
    """benchmarks/NAME.py as a module, NAME may name a subfolder (reports/pilot_table); benchmarks/ is not a package,
    its folder goes on sys.path, so a script imports its siblings, `from bench_generation import ...`, as when run."""
    folder = str(REPO / "benchmarks")
    if folder not in sys.path:
        sys.path.append(folder)
    spec = importlib.util.spec_from_file_location(Path(name).name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def diffusion_config(world: tuple[Path, Path], out: Path, stage: str, *extra: str) -> DiffusionTrainConfig:
    """configs/u4d/tiny.yaml on (scans root, probabilities root), writing to `out`, as `stage`, + overrides."""
    overrides = [
        f"data_root={world[0]}",
        f"probs_root={world[1]}",
        f"out={out}",
        *split_stage_override([f"stage={stage}"]),
        *extra,
    ]
    return load_config(DiffusionTrainConfig, TINY, overrides)


def extractor_config(root: Path, out: Path, seed: int = 0) -> ExtractorConfig:
    """configs/extractor/tiny.yaml on `root`, writing to `out`, with the training seed."""
    return load_config(ExtractorConfig, EXTRACTOR_TINY, [f"data.root={root}", f"out_dir={out}", f"train.seed={seed}"])


# `u4d generate` sampling keys of plain sampling: one step count, no stage-1 mask cap, no mean start
PLAIN_SAMPLING = ("stage1_steps=null", "stage1_mask_fraction=null", "mean_start_below=null")


def gen_config(checkpoints: dict[str, Path], *overrides: str) -> GenerateConfig:
    """A `u4d generate` config of the three stage checkpoints: DDPM at 2 steps (`PLAIN_SAMPLING`) on the CPU, seed
    100, + overrides."""
    base = [f"stage1={checkpoints['stage1']}", f"stage2={checkpoints['stage2']}"]
    base += [f"baseline={checkpoints['baseline']}", "sampler=ddpm", "steps=2", *PLAIN_SAMPLING]
    base += ["device=cpu", "seed=100"]
    return load_config(GenerateConfig, None, [*base, *overrides])


def plain_settings(steps: int, sampler: str = "ddim", **options) -> SamplingSettings:
    """`sampler` at `steps` for every stage, no stage-1 mask cap, no mean start (nets without a stored mean), + options
    (SamplingSettings fields)."""
    fields = {"stage1_steps": None, "stage1_mask_fraction": None, "mean_start_below": None, **options}
    return SamplingSettings(sampler=sampler, steps=steps, **fields)


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


def save_random_checkpoint(path: Path, stage: str, seed: int = 0, config: Path = TINY) -> Path:
    """A tiny-config checkpoint whose EMA weights are random (untrained output convs are zero, which would
    make every sample ignore its input); the raw model weights are zeroed so only EMA loading gives them."""
    cfg = load_config(DiffusionTrainConfig, config, [f"diffusion.stage={stage}"])
    net = build_net(cfg)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in net.parameters():
            param.add_(torch.randn(param.shape, generator=generator) * 0.2)
        if net.mask_conv is not None:
            net.mask_conv.bias.fill_(0.3)  # roughly half of the pixels above sigmoid 0.5
    ema = EMA(net)
    with torch.no_grad():
        for param in net.parameters():
            param.zero_()
    atomic_torch_save(path, checkpoint_state(cfg, 0, net, ema))
    return path


def torchrun(*argv: str, timeout: float = 240) -> subprocess.CompletedProcess:
    """`python -m torch.distributed.run --nproc_per_node 2 --standalone ...` with one thread per process."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--standalone", *argv]
    result = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, result.stderr[-3000:]
    return result
