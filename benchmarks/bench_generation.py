"""U4D vs the R2DM-style baseline on the simulated world: Table 1 metrics per seed, mean ± std, real-vs-real floor.

    python benchmarks/bench_generation.py --root /work/runs/sim --stage1 runs/u4d_stage1 --stage2 runs/u4d_stage2 \
        --baseline runs/baseline --reference 07 --floor 06 --num 64 --seeds 0 1 2 \
        [--extractor-frd frd.pt --extractor-fpd fpd.pt] [--steps 32 --stage1-steps 8]
    python benchmarks/bench_generation.py ... --quick            # 8 scans, seeds 0 1, 8 steps

Train the generators first with one budget for each method (U4D's budget = stage 1 + stage 2; the baseline
gets the same wall clock or steps x batch), e.g. `u4d train-diffusion configs/u4d/cpu.yaml stage=baseline
max_minutes=40`; the training budgets read from the checkpoints are printed with the table.
Per seed s: each method generates `--num` scans (sample i uses seed s * 100000 + i) into
OUT/banks/<method>_s<s>, scored by `u4d_aug.metrics.evaluate.evaluate` against the held-out reference
sequences; the floor draws `--num` scans of the `--floor` sequences (disjoint from the reference) with seed s
and scores them the same way, so it is the value a perfect generator would get at this sample size.
Sampler: ancestral DDPM by default, as R2DM samples (256 steps there). With nets trained for minutes on a CPU,
deterministic DDIM at few steps keeps the high-frequency noise of x_1 (measured on the 4000-step CPU baseline,
32x256: mean |horizontal depth difference| 0.18 with DDIM 16 steps and 0.21 with 256, 0.034 with DDPM 32,
0.019 on simulated scans), so DDIM is for speed comparisons rather than quality.
Writes benchmarks/results/generation.json and generation.md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from u4d_aug.config import load_config
from u4d_aug.data.datasets import list_frames
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text, load_checkpoint
from u4d_aug.metrics.evaluate import evaluate
from u4d_aug.pipeline import load_generator

REPO = Path(__file__).resolve().parents[1]
METHODS = ("u4d", "baseline")
SEED_STRIDE = 100_000


def training_budget(run: Path) -> dict:
    """Steps, batch, wall-clock minutes and net size of the newest checkpoint of a train-diffusion run."""
    path = run
    if run.is_dir():
        found = sorted((run / "checkpoints").glob("step_*.pt"))
        if not found:
            raise InputError(f"{run}: no checkpoints/step_*.pt (train it with `u4d train-diffusion`)")
        path = found[-1]
    ckpt = load_checkpoint(path, "diffusion checkpoint")
    cfg = ckpt["config"]
    return {
        "checkpoint": str(path),
        "stage": cfg["diffusion"]["stage"],
        "steps": int(ckpt["step"]),
        "batch_size": cfg["batch_size"],
        "minutes": round(float(ckpt.get("elapsed", 0.0)) / 60.0, 2),
        "params": sum(p.numel() for p in load_generator(path)[0].parameters()),  # not buffers (ray features)
        "size": [cfg["height"], cfg["width"]],
    }


def floor_bank(root: Path, sequences: list[str], num: int, seed: int, out: Path) -> Path:
    """A 'bank' of `num` real scans of `sequences` drawn with `seed`: symlinks in SemanticKITTI layout."""
    entries = [(seq, frame) for seq in sequences for frame in list_frames(root, seq)]
    if len(entries) < num:
        raise InputError(f"--floor {' '.join(sequences)}: {len(entries)} scans, fewer than --num {num}")
    chosen = np.random.default_rng(seed).choice(len(entries), num, replace=False)
    velodyne = out / "sequences" / "00" / "velodyne"
    velodyne.mkdir(parents=True, exist_ok=True)
    for i, index in enumerate(sorted(chosen)):
        seq, frame = entries[index]
        link = velodyne / f"{i:06d}.bin"
        if not link.exists():
            link.symlink_to((root / "sequences" / seq / "velodyne" / f"{frame}.bin").resolve())
    return out


def generate(method: str, args: argparse.Namespace, seed: int, out: Path) -> float:
    """Generate this method's bank for one seed (resumable); returns seconds per newly generated scan."""
    overrides = [f"mode={method}", f"num={args.num}", f"seed={seed * SEED_STRIDE}", f"steps={args.steps}"]
    overrides += [f"device={args.device}", f"sampler={args.sampler}"]
    if method == "u4d":
        overrides += [f"stage1={args.stage1}", f"stage2={args.stage2}", f"stage1_steps={args.stage1_steps}"]
    else:
        overrides.append(f"baseline={args.baseline}")
    cfg = load_config(GenerateConfig, None, overrides)
    before = len(list((out / "sequences" / "00" / "velodyne").glob("*.bin"))) if out.exists() else 0
    start = time.perf_counter()
    generate_bank(cfg, out, progress=True)
    new = args.num - before
    timing = out / "bench_timing.json"  # a reused bank keeps the speed measured when it was generated
    if new > 0:
        atomic_write_json(timing, {"seconds_per_scan": (time.perf_counter() - start) / new, "scans": new})
    return json.loads(timing.read_text())["seconds_per_scan"] if timing.exists() else float("nan")


def summarise(values: list[float | None]) -> dict:
    """mean, std (sample, 0 for one value), and the per-seed values; None entries are skipped."""
    kept = [v for v in values if v is not None and np.isfinite(v)]
    if not kept:
        return {"mean": None, "std": None, "values": values}
    std = statistics.stdev(kept) if len(kept) > 1 else 0.0
    return {"mean": statistics.fmean(kept), "std": std, "values": values}


def to_markdown(result: dict) -> str:
    """One table: rows = methods + floor, columns = metrics as mean ± std over seeds."""
    metrics, sampler = result["metrics"], result["sampler"]
    header = {"frd": "FRD ↓", "fpd": "FPD ↓", "jsd": "JSD ↓", "mmd": "MMD ×10⁴ ↓"}
    lines = [
        f"# Generation benchmark: {result['num']} scans per seed, seeds {result['seeds']}, "
        f"reference sequences {result['reference']} of `{result['root']}`, "
        f"{sampler['name']} {sampler['steps']} steps (stage 1: {sampler['stage1_steps']})",
        "",
        "| method | " + " | ".join(header[m] for m in metrics) + " | s/scan |",
        "|---" * (len(metrics) + 2) + "|",
    ]
    for name, row in result["rows"].items():
        cells = []
        for metric in metrics:
            s = row[metric]
            cells.append("—" if s["mean"] is None else f"{s['mean']:.4g} ± {s['std']:.2g}")
        speed = row.get("seconds_per_scan", {}).get("mean")
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {'—' if speed is None else f'{speed:.2f}'} |")
    lines += ["", "Training budgets:", ""]
    for name, budget in result["training"].items():
        lines.append(
            f"- {name}: {budget['steps']} steps x batch {budget['batch_size']}, {budget['minutes']} min, "
            f"{budget['params']:,} params, {budget['size'][0]}x{budget['size'][1]}"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="simulated SemanticKITTI root")
    parser.add_argument("--stage1", type=Path, required=True, help="U4D stage-1 run folder or checkpoint")
    parser.add_argument("--stage2", type=Path, required=True, help="U4D stage-2 run folder or checkpoint")
    parser.add_argument("--baseline", type=Path, required=True, help="baseline run folder or checkpoint")
    parser.add_argument("--reference", nargs="+", default=["07"], help="held-out sequences scored against")
    parser.add_argument("--floor", nargs="+", default=["06"], help="other held-out sequences: real-vs-real floor")
    parser.add_argument("--num", type=int, default=64, help="scans per method and seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--sampler", choices=("ddpm", "ddim", "dpmpp2m"), default="ddpm", help="R2DM samples with ddpm")
    parser.add_argument("--steps", type=int, default=32, help="sampler steps (baseline and stage 2)")
    parser.add_argument("--stage1-steps", type=int, default=8, help="sampler steps of stage 1")
    parser.add_argument("--metrics", default="jsd,mmd", help="subset of frd,fpd,jsd,mmd")
    parser.add_argument("--extractor-frd", type=Path, default=None)
    parser.add_argument("--extractor-fpd", type=Path, default=None)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--work", type=Path, default=REPO / "runs" / "bench_generation", help="banks go here")
    parser.add_argument("--quick", action="store_true", help="8 scans, seeds 0 1, 8 steps (stage 1: 4)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "generation.json")
    args = parser.parse_args(argv)
    if args.quick:
        args.num, args.seeds, args.steps, args.stage1_steps = 8, [0, 1], 8, 4
    metrics = tuple(m.strip() for m in args.metrics.split(",") if m.strip())
    try:
        training = {
            "u4d stage 1": training_budget(args.stage1),
            "u4d stage 2": training_budget(args.stage2),
            "baseline": training_budget(args.baseline),
        }
        rows: dict[str, dict[str, list]] = {name: {m: [] for m in metrics} for name in (*METHODS, "real floor")}
        speed: dict[str, list[float]] = {name: [] for name in METHODS}
        for seed in args.seeds:
            tag = f"{args.sampler}{args.steps}"  # banks of another sampler or step count are not reused
            banks = {name: args.work / f"{name}_{tag}_s{seed}" for name in METHODS}
            for name in METHODS:
                print(f"seed {seed}: generating {args.num} scans with {name}", flush=True)
                speed[name].append(generate(name, args, seed, banks[name]))
            banks["real floor"] = floor_bank(args.root, args.floor, args.num, seed, args.work / f"floor_s{seed}")
            for name, bank in banks.items():
                result = evaluate(
                    bank, args.root, metrics, None, args.extractor_frd, args.extractor_fpd, args.reference
                )
                for metric in metrics:
                    rows[name][metric].append(result["table1"][metric]["value"])
                print(f"seed {seed} {name}: " + ", ".join(f"{m}={rows[name][m][-1]}" for m in metrics), flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = {
        "benchmark": "generation",
        "command": " ".join(sys.argv),
        "machine": host_info(),
        "root": str(args.root),
        "reference": args.reference,
        "floor_sequences": args.floor,
        "num": args.num,
        "seeds": args.seeds,
        "sampler": {"name": args.sampler, "steps": args.steps, "stage1_steps": args.stage1_steps},
        "metrics": list(metrics),
        "training": training,
        "rows": {
            name: {m: summarise(values[m]) for m in metrics}
            | ({"seconds_per_scan": summarise(speed[name])} if name in speed else {})
            for name, values in rows.items()
        },
    }
    text = to_markdown(result)
    print(text)
    atomic_write_json(args.out, result)
    atomic_write_text(args.out.with_suffix(".md"), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
