"""`u4d generate CONFIG --out BANK [--num N] [--mode u4d|baseline|complete] [--steps S] [--seed S]`.

Writes a bank of generated scans (layout in `u4d_aug.bank`). Sample i is drawn with its own generator seeded
seed + i, so a bank does not depend on the number of torchrun ranks that share the work (rank r takes samples
r, r + world, ...); finished samples are skipped on a re-run.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from tqdm.auto import tqdm

from u4d_aug.bank import BankLayout, check_compatible, file_sha256, read_manifest, write_manifest, write_sample
from u4d_aug.config import config_to_dict, load_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.sensors import get_sensor
from u4d_aug.distributed import barrier, cleanup, init_distributed, shard
from u4d_aug.errors import InputError
from u4d_aug.pipeline import Sampler, complete, generate_baseline, generate_u4d, load_generator, to_points
from u4d_aug.train import DiffusionTrainConfig
from u4d_aug.uncertainty import load_probs, probs_path, uncertain_range_view

Mode = Literal["u4d", "baseline", "complete"]


@dataclass
class GenerateConfig:
    """What to generate and with which checkpoints (checkpoint files or run folders: newest step_*.pt)."""

    mode: Mode = "u4d"
    stage1: str = ""  # u4d mode
    stage2: str = ""  # u4d and complete modes
    baseline: str = ""  # baseline mode
    sampler: Sampler = "ddim"
    steps: int = 32
    stage1_steps: int | None = None  # None = steps; the uncertain region allows fewer
    num: int = 64
    seed: int = 0  # sample i uses seed + i
    device: str = "auto"
    # completion mode: x0_u, m_u from these real scans (sample i completes scan i mod count) and their probs
    data_root: str = ""
    sequences: list[str] | None = None
    probs_root: str = ""

    def __post_init__(self) -> None:
        if self.num < 0 or self.steps < 1 or (self.stage1_steps is not None and self.stage1_steps < 1):
            raise InputError(f"num must be >= 0 and steps >= 1, got num={self.num}, steps={self.steps}")


def _checkpoint_paths(cfg: GenerateConfig) -> dict[str, Path]:
    needed = {"u4d": ("stage1", "stage2"), "baseline": ("baseline",), "complete": ("stage2",)}[cfg.mode]
    paths = {}
    for name in needed:
        value = getattr(cfg, name)
        if not value:
            raise InputError(f"{name}: mode {cfg.mode} needs the {name} checkpoint path")
        path = Path(value)
        if path.is_dir():
            found = sorted((path / "checkpoints").glob("step_*.pt"))
            if not found:
                raise InputError(f"{path}: no checkpoints/step_*.pt in this run folder")
            path = found[-1]
        if not path.is_file():
            raise InputError(f"{path}: {name} checkpoint not found")
        paths[name] = path
    return paths


def generate_bank(cfg: GenerateConfig, out: str | Path, progress: bool = True) -> dict:
    """Generate samples 0..num-1 not yet in the bank (this rank's share); rank 0 writes the manifest."""
    info = init_distributed(cfg.device)
    layout = BankLayout(Path(out))
    paths = _checkpoint_paths(cfg)
    hashes = {name: file_sha256(path) for name, path in paths.items()}
    config = config_to_dict(cfg)
    identity = {"mode": cfg.mode, "checkpoints": hashes, "seed": cfg.seed,
                "sampling": {k: config[k] for k in ("sampler", "steps", "stage1_steps")}}  # fmt: skip
    if cfg.mode == "complete":
        identity["source"] = {k: config[k] for k in ("data_root", "sequences", "probs_root")}
    check_compatible(layout.root, identity)
    nets = {name: load_generator(path, info.device) for name, path in paths.items()}
    main = nets["stage2"] if "stage2" in nets else nets["baseline"]
    sensor = get_sensor(main[1].sensor)

    scans = None
    if cfg.mode == "complete":
        if not cfg.data_root:
            raise InputError("data_root: completion mode needs real scans to take x0_u from")
        scans = ScanDataset(cfg.data_root, cfg.sequences)
        if len(scans) == 0:
            raise InputError(f"{cfg.data_root}: no scans found")

    manifest = {
        **identity,
        "config": config,
        "checkpoint_paths": {name: str(path) for name, path in paths.items()},
        "sensor": main[1].sensor,
        "height": main[1].height,
        "width": main[1].width,
        "row_mode": main[1].row_mode,
        "samples": [_sample_entry(cfg, i, scans) for i in range(cfg.num)],
        "complete": False,
    }
    old = read_manifest(layout.root)
    if old is not None and len(old.get("samples", [])) > cfg.num:
        manifest["samples"] = old["samples"]  # a re-run asking for fewer samples keeps the larger listing
    if info.is_main:
        write_manifest(layout.root, manifest)

    todo = [i for i in shard(list(range(cfg.num)), info.rank, info.world_size) if not layout.is_done(i)]
    for i in tqdm(todo, disable=not (progress and info.is_main), desc=f"generate {cfg.mode}"):
        generator = torch.Generator().manual_seed(cfg.seed + i)
        mask = uncertainty = x0_u = None
        if cfg.mode == "u4d":
            result = generate_u4d(
                nets["stage1"], nets["stage2"], 1, cfg.steps, generator, cfg.sampler, cfg.stage1_steps
            )
            mask, x0_u = result["m_u_pred"][0, 0].cpu().numpy(), result["x0_u"][0].cpu().numpy()
        elif cfg.mode == "baseline":
            result = generate_baseline(nets["baseline"], 1, cfg.steps, generator, cfg.sampler)
        else:
            x0_u, m_u, entropy_image = _real_condition(scans, i, main[1], cfg.probs_root, generator)
            result = complete(nets["stage2"], x0_u[None], m_u[None], cfg.steps, generator, cfg.sampler)
            mask, uncertainty, x0_u = m_u[0].numpy(), entropy_image.numpy(), x0_u.numpy()
        (points,) = to_points(result["x0"], sensor, main[1].row_mode)
        write_sample(layout, i, points, mask, uncertainty, x0_u)

    barrier()
    if info.is_main:
        manifest["complete"] = all(layout.is_done(i) for i in range(cfg.num))
        manifest["empty"] = [i for i in range(cfg.num) if layout.is_empty(i)]
        write_manifest(layout.root, manifest)
    return manifest


def _sample_entry(cfg: GenerateConfig, index: int, scans: ScanDataset | None) -> dict:
    entry: dict = {"index": index, "seed": cfg.seed + index, "file": f"sequences/00/velodyne/{index:06d}.bin"}
    if scans is not None:
        seq, frame = scans.entries[index % len(scans)]
        entry["source"] = f"{seq}/{frame}"
    return entry


def _real_condition(scans: ScanDataset, index: int, train_cfg: DiffusionTrainConfig, probs_root: str, generator):
    """x0_u (2, H, W), m_u (1, H, W), entropy image (H, W) of real scan index mod count, as stage 2 was trained."""
    item = scans[index % len(scans)]
    points = torch.from_numpy(item["points"])
    strategy = train_cfg.uncertainty.strategy
    if strategy == "none":
        probs = np.zeros((points.shape[0], 1), dtype=np.float32)
    else:
        root = probs_root or train_cfg.probs_root
        if not root:
            raise InputError("probs_root: completion mode needs the probability files of the real scans")
        probs = load_probs(probs_path(root, item["seq"], item["frame"]), points.shape[0])
    sensor = get_sensor(train_cfg.sensor)
    return uncertain_range_view(
        points, probs, sensor, train_cfg.height, train_cfg.width, train_cfg.row_mode,
        train_cfg.uncertainty.k, strategy, generator,
    )  # fmt: skip


def add_generate_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d generate CONFIG --out BANK [--num N] [--mode ...] [--steps S] [--seed S] [key=value ..]`."""
    parser.add_argument("config", type=Path, help="yaml naming the checkpoints, sampler and steps")
    parser.add_argument("overrides", nargs="*", help="key=value overrides, e.g. stage1=runs/s1 sampler=ddpm")
    parser.add_argument("--out", type=Path, required=True, help="bank folder (SemanticKITTI layout)")
    parser.add_argument("--num", type=int, default=None, help="number of scans (default: the config's num)")
    parser.add_argument("--mode", choices=["u4d", "baseline", "complete"], default=None)
    parser.add_argument("--steps", type=int, default=None, help="sampling steps")
    parser.add_argument("--seed", type=int, default=None, help="base seed: sample i uses seed + i")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_generate(args: argparse.Namespace) -> int:
    """`u4d generate`: write a bank of generated scans (torchrun shards the samples across ranks)."""
    overrides = list(args.overrides)
    for key in ("num", "mode", "steps", "seed"):
        if getattr(args, key) is not None:
            overrides.append(f"{key}={getattr(args, key)}")
    cfg = load_config(GenerateConfig, args.config, overrides)
    try:
        generate_bank(cfg, args.out, progress=not args.no_progress)
    finally:
        cleanup()
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m u4d_aug.generate CONFIG ...`: the same as `u4d generate`, handy under torchrun."""
    parser = argparse.ArgumentParser(prog="python -m u4d_aug.generate", description=run_generate.__doc__)
    add_generate_arguments(parser)
    try:
        return run_generate(parser.parse_args(argv))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
