"""Which sampler, how many steps: sample quality proxies and time per scan of one trained net, several samplers.

    python benchmarks/bench_samplers.py runs/gen64/baseline --samplers ddpm:32 dpmpp2m-sde:20 dpmpp2m-sde:10 \
        dpmpp2m:20 ddim:20 --num 4 --real data/sim_eval --out benchmarks/results/generation/samplers_64x1024.json

For a baseline or stage-1 net (unconditional), each NAME:STEPS[:GRID] setting draws `--num` range images (sample i
seeded i, the same for every setting) and reports, against real scans projected the same way:
- roughness (`range_view.image_roughness`): mean |depth difference| of horizontally adjacent pixels that both hold a
  return (encoded depth in [-1, 1]); the noise a deterministic solver keeps from x_1 shows up here first,
- returns: the share of pixels holding a return (real scans: ~85 % at 64x1024),
- seconds per scan (wall clock of the sampling call / num).
These are fast proxies to choose a sampler before the Table-1 benchmark (`bench_generation.py`), not its metrics.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text
from u4d_aug.range_view import image_roughness

REPO = Path(__file__).resolve().parents[1]


def real_images(root: Path, cfg, num: int) -> torch.Tensor:
    """The first `num` scans of a SemanticKITTI root as the net's range images (N, 2, H, W)."""
    from u4d_aug.data.datasets import ScanDataset
    from u4d_aug.data.sensors import get_sensor
    from u4d_aug.range_view import project, to_image

    sensor = get_sensor(cfg.sensor)
    scans = ScanDataset(root)
    if len(scans) == 0:
        raise InputError(f"{root}: no scans")
    images = []
    for index in range(min(num, len(scans))):
        points = torch.from_numpy(scans[index]["points"])
        images.append(to_image(project(points, sensor, cfg.height, cfg.width, cfg.row_mode), sensor))
    return torch.stack(images)


def run_setting(loaded, spec: str, num: int) -> dict:
    """Sample `num` images with one NAME:STEPS[:GRID] setting; its proxies and seconds per scan."""
    from u4d_aug.pipeline import generate_baseline, generate_stage1
    from u4d_aug.sampling_settings import SamplingSettings

    parts = spec.split(":")
    if len(parts) not in (2, 3) or not parts[1].isdigit():
        raise InputError(f"--samplers {spec!r}: expected NAME:STEPS[:GRID], e.g. dpmpp2m-sde:20")
    name, steps, grid = parts[0], int(parts[1]), parts[2] if len(parts) == 3 else "time"
    # the sampler alone: every step from the net's own x̂0 (no mean start), no stage-1 mask cap
    settings = SamplingSettings(
        sampler=name, grid=grid, steps=steps, stage1_steps=None, stage1_mask_fraction=None, mean_start_below=None
    )
    generators = [torch.Generator().manual_seed(i) for i in range(num)]
    stage = loaded.config.diffusion.stage
    start = time.perf_counter()
    if stage == "baseline":
        x0 = generate_baseline(loaded, num, generators, settings)["x0"]
    elif stage == "stage1":
        x0 = generate_stage1(loaded, num, generators, settings)["x0_u"]
    else:
        raise InputError(f"bench_samplers: needs an unconditional net (baseline or stage1), got {stage}")
    seconds = (time.perf_counter() - start) / num
    rough, returns = image_roughness(x0)
    return {
        "sampler": name,
        "steps": steps,
        "grid": grid,
        "roughness": rough,
        "returns": returns,
        "s_per_scan": seconds,
    }


def to_markdown(result: dict) -> str:
    """One row per setting, the real scans first."""
    real = result["real"]
    lines = [
        f"# Samplers on `{result['checkpoint']}` ({result['stage']}, step {result['step']}), {result['num']} scans",
        "",
        "| setting | roughness | returns | s/scan |",
        "|---|---|---|---|",
        f"| real scans | {real['roughness']:.4f} | {real['returns']:.3f} | — |",
    ]
    for row in result["settings"]:
        grid = "" if row["grid"] == "time" else f" ({row['grid']})"
        lines.append(
            f"| {row['sampler']} {row['steps']}{grid} | {row['roughness']:.4f} | {row['returns']:.3f} | "
            f"{row['s_per_scan']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="baseline or stage-1 run folder, checkpoint or exported weights")
    parser.add_argument("--samplers", nargs="+", default=["ddpm:32", "dpmpp2m-sde:20", "dpmpp2m:20", "ddim:20"])
    parser.add_argument("--num", type=int, default=4, help="scans per setting")
    parser.add_argument("--real", type=Path, required=True, help="SemanticKITTI root of real scans to compare with")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "generation" / "samplers.json")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        from u4d_aug.io import load_checkpoint
        from u4d_aug.pipeline import load_generator
        from u4d_aug.run import newest_checkpoint

        if args.num < 1:
            raise InputError(f"--num must be >= 1, got {args.num}")
        loaded = load_generator(args.checkpoint)
        path = newest_checkpoint(args.checkpoint) if args.checkpoint.is_dir() else args.checkpoint
        state = load_checkpoint(path, "diffusion checkpoint")
        step = state.get("step", state.get("trained", {}).get("step"))
        rough, returns = image_roughness(real_images(args.real, loaded.config, args.num))
        settings = [run_setting(loaded, spec, args.num) for spec in args.samplers]
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = {
        "benchmark": "samplers",
        "command": " ".join(sys.argv),
        "machine": host_info(),
        "checkpoint": str(args.checkpoint),
        "stage": loaded.config.diffusion.stage,
        "step": step,
        "num": args.num,
        "real": {"root": str(args.real), "roughness": rough, "returns": returns},
        "settings": settings,
    }
    text = to_markdown(result)
    print(text)
    atomic_write_json(args.out, result)
    atomic_write_text(args.out.with_suffix(".md"), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
