"""Semi-supervised (LaserMix mean teacher) vs supervised training step: steps/s and peak memory, same scans.

    python benchmarks/bench_semisup.py            # full real scans, 5 timed steps per case
    python benchmarks/bench_semisup.py --quick    # scans subsampled to 30k points, 2 timed steps

Scans: the real SemanticKITTI sequence 00 of ../shared/data/real (3 labeled + 3 unlabeled scans). Both modes
use the configs/seg/cpu_semi.yaml preset (MinkUNet-like, 0.2 m voxels, W16, batch 2) with label_fraction 1,
so that the B labeled scans of step s are the same in both modes; mode "semi" adds B unlabeled scans (drawn
from all 6 scans), the teacher's forward on them, 2B LaserMix scans and the EMA update. A step = forward +
backward + AdamW step (+ EMA), batches loaded beforehand (loading is not timed); steps/s = 1 / median step
time after one warm-up step. Memory: one subprocess per case; the peak-RSS mark is reset (`5` written to
/proc/self/clear_refs) after set-up, extra memory = VmHWM at the end minus VmRSS at the reset.
Writes benchmarks/results/segmentation/semisup.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from peak_memory import peak_mb, run_case, start_memory_window

from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "data" / "real" / "semantickitti"
PRESET = REPO / "configs" / "seg" / "cpu_semi.yaml"


def child(args: argparse.Namespace) -> dict:
    """One case in this process: `args.mode` steps on the preset, timed, with the memory they add."""
    from segmentation.batches import TrainBatches, train_scans
    from segmentation.config import SegTrainConfig
    from segmentation.mean_teacher import make_teacher, teacher_mode
    from segmentation.models import build_model
    from segmentation.optimizer import make_optimizer
    from segmentation.semi import semi_step, unlabeled_stream, update_teacher
    from segmentation.train import supervised_step
    from u4d_aug.config import load_config
    from u4d_aug.distributed import DistInfo

    overrides = [f"data.root={REAL}", "data.train_sequences=['00']", "data.label_fraction=1.0", f"mode={args.mode}"]
    overrides.append(f"data.max_points={args.max_points or 'null'}")  # the preset's own subset otherwise
    overrides.append("semi.burn_in_steps=0")  # every timed step is a mean-teacher step
    cfg = load_config(SegTrainConfig, PRESET, overrides)
    device = torch.device("cpu")
    scans = train_scans(cfg, DistInfo(0, 1, 0, device))
    stream = unlabeled_stream(cfg) if cfg.mode == "semi" else None
    batches = [TrainBatches(scans, cfg, 0, 1, stream)[step] for step in range(args.steps + 1)]
    torch.manual_seed(0)
    model = build_model(cfg.model)
    teacher = teacher_mode(make_teacher(model), cfg.semi.bn_mode) if cfg.mode == "semi" else None
    optimizer = make_optimizer(model, cfg.optim)
    model.train()
    before = start_memory_window()
    times = []
    for i, batch in enumerate(batches):
        start = time.perf_counter()
        if teacher is None:
            losses = supervised_step(model, batch, cfg, device)
        else:
            losses = semi_step(model, teacher, batch, cfg, device)
        optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        optimizer.step()
        if teacher is not None:
            update_teacher(teacher, model, cfg.semi, i)
        if i:  # step 0 is the warm-up
            times.append(time.perf_counter() - start)
    points = [sum(p.shape[0] for p in b["points"] + b.get("unlabeled", [])) for b in batches[1:]]
    return {
        "mode": args.mode,
        "median_step_s": statistics.median(times),
        "steps_per_s": 1.0 / statistics.median(times),
        "timed_steps": len(times),
        "extra_peak_mb": peak_mb() - before,
        "input_points_per_step": statistics.median(points),
    }


def run_child(mode: str, args: argparse.Namespace) -> dict:
    argv = ["--child", mode, "--threads", str(args.threads), "--steps", str(args.steps)]
    if args.max_points:
        argv += ["--max-points", str(args.max_points)]
    return run_case(__file__, argv, f"{mode} case")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="30k-point scans, 2 timed steps")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=None, help="timed steps per case (after one warm-up)")
    parser.add_argument("--max-points", type=int, default=None, help="subsample scans (default: full; quick: 30000)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "semisup.json")
    parser.add_argument("--child", choices=["supervised", "semi"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    args.steps = args.steps or (2 if args.quick else 5)
    if args.max_points is None and args.quick:
        args.max_points = 30000
    if args.child:
        args.mode = args.child
        print(json.dumps(child(args)))
        return 0
    if not (REAL / "sequences" / "00" / "velodyne" / "000000.bin").is_file():
        print(f"real scans not found at {REAL}", file=sys.stderr)
        return 1

    rows = [run_child(mode, args) for mode in ("supervised", "semi")]
    sup, semi = rows
    ratio = semi["median_step_s"] / sup["median_step_s"]
    print(f"{'mode':<11} {'steps/s':>8} {'step s':>8} {'points/step':>12} {'extra peak MB':>14}")
    for r in rows:
        print(
            f"{r['mode']:<11} {r['steps_per_s']:>8.3f} {r['median_step_s']:>8.3f} "
            f"{r['input_points_per_step']:>12.0f} {r['extra_peak_mb']:>14.1f}"
        )
    print(f"semi step / supervised step: {ratio:.2f}x the time")
    atomic_write_json(
        args.out,
        {
            "command": " ".join(["python", "benchmarks/bench_semisup.py", *sys.argv[1:]]),
            "machine": host_info(),
            "threads": args.threads,
            "preset": str(PRESET.relative_to(REPO)),
            "max_points": args.max_points,
            "memory_method": "VmHWM after a clear_refs reset minus VmRSS before; one subprocess per case",
            "rows": rows,
            "semi_over_supervised_step_time": ratio,
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
