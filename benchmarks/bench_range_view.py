"""Range-view throughput (scans/s) and round-trip error on the real 124,668-point KITTI scan, both row modes.

    python benchmarks/bench_range_view.py            # 64x1024 and 64x2048, beam and linear, 2 torch threads
    python benchmarks/bench_range_view.py --quick    # fewer repetitions

project = points -> Projection -> (2, H, W) image (`project` + `to_image`); unproject = image -> points;
batch = `project_batch` of B copies of the scan, in scans/s. Medians over repetitions after a warm-up.
Writes benchmarks/results/speed/range_view.json. Goal: >= 50 scans/s projection on 2 cores.
On a machine shared with other busy processes, 2 OpenMP threads that spin-wait can slow each op by 10-50x;
`OMP_WAIT_POLICY=PASSIVE python benchmarks/bench_range_view.py` (or --threads 1) shows the uncontended cost.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from u4d_aug.data.sensors import hdl64
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json
from u4d_aug.range_view import project, project_batch, roundtrip_stats, to_image, unproject

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SCAN = (
    REPO.parent / "shared" / "data" / "real" / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin"
)
CONFIGS = [(64, 1024, "beam"), (64, 1024, "linear"), (64, 2048, "beam"), (64, 2048, "linear")]


def time_calls(function, num_calls: int) -> float:
    """Seconds per call of `function` over `num_calls` calls."""
    start = time.perf_counter()
    for _ in range(num_calls):
        function()
    return (time.perf_counter() - start) / num_calls


def make_tasks(points: torch.Tensor, args: argparse.Namespace) -> dict[tuple, tuple]:
    """(H, W, row_mode, measure) -> (function, scans per call, calls per repetition)."""
    sensor = hdl64()
    batch = [points] * args.batch
    tasks = {}
    for height, width, row_mode in CONFIGS:
        image = to_image(project(points, sensor, height, width, row_mode), sensor)
        tasks[(height, width, row_mode, "project")] = (
            functools.partial(_project_image, points, sensor, height, width, row_mode),
            1,
            args.calls,
        )
        tasks[(height, width, row_mode, "unproject")] = (
            functools.partial(unproject, image, sensor, row_mode),
            1,
            args.calls,
        )
        tasks[(height, width, row_mode, "batch")] = (
            functools.partial(_project_batch_image, batch, sensor, height, width, row_mode),
            args.batch,
            max(args.calls // args.batch, 1),
        )
    return tasks


def _project_image(points, sensor, height, width, row_mode) -> torch.Tensor:
    return to_image(project(points, sensor, height, width, row_mode), sensor)


def _project_batch_image(scans, sensor, height, width, row_mode) -> torch.Tensor:
    return to_image(project_batch(scans, sensor, height, width, row_mode), sensor)


def run(points: torch.Tensor, args: argparse.Namespace) -> list[dict]:
    """Repetitions interleave all configs, so a burst of load from other processes hits every config alike."""
    tasks = make_tasks(points, args)
    for function, _, _ in tasks.values():
        for _ in range(args.warmup):
            function()
    rates: dict[tuple, list[float]] = {key: [] for key in tasks}
    for _ in range(args.reps):
        for key, (function, scans_per_call, num_calls) in tasks.items():
            rates[key].append(scans_per_call / time_calls(function, num_calls))
    rows = []
    for height, width, row_mode in CONFIGS:
        median = {m: statistics.median(rates[(height, width, row_mode, m)]) for m in ("project", "unproject", "batch")}
        rows.append(
            {
                "height": height,
                "width": width,
                "row_mode": row_mode,
                "project_scans_per_s": median["project"],
                "unproject_scans_per_s": median["unproject"],
                f"project_batch{args.batch}_scans_per_s": median["batch"],
                **roundtrip_stats(points, hdl64(), height, width, row_mode),
                "reps": args.reps,
                "calls_per_rep": args.calls,
            }
        )
    return rows


def print_table(rows: list[dict], args: argparse.Namespace, num_points: int, load_before: float) -> None:
    batch_key = f"project_batch{args.batch}_scans_per_s"
    policy = os.environ.get("OMP_WAIT_POLICY", "default")
    print(f"range view on {args.scan.name}: {num_points} points, torch {torch.__version__}")
    print(f"{args.threads} threads, OMP_WAIT_POLICY {policy}, load average before {load_before:.2f}")
    header = (
        f"{'H x W':>11} {'rows':>6} | {'project/s':>9} {f'batch{args.batch}/s':>9} {'unproj/s':>9} | "
        f"{'kept':>6} {'median m':>9} {'p99 m':>7}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        size = f"{row['height']} x {row['width']}"
        print(
            f"{size:>11} {row['row_mode']:>6} | {row['project_scans_per_s']:>9.1f} {row[batch_key]:>9.1f} "
            f"{row['unproject_scans_per_s']:>9.1f} | {row['kept_fraction']:>6.3f} "
            f"{row['median_error_m']:>9.4f} {row['p99_error_m']:>7.3f}"
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scan", type=Path, default=DEFAULT_SCAN, help="KITTI .bin scan (default: real frame 0)")
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    parser.add_argument("--reps", type=int, default=7, help="timed repetitions; the median is reported")
    parser.add_argument("--calls", type=int, default=16, help="calls per repetition")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--batch", type=int, default=8, help="scans per project_batch call")
    parser.add_argument("--quick", action="store_true", help="5 reps of 4 calls")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "speed" / "range_view.json")
    args = parser.parse_args()
    if args.quick:
        args.reps, args.calls, args.warmup = 5, 4, 1
    if not args.scan.is_file():
        parser.error(f"scan not found: {args.scan} (the real scans live in ../shared/data/real)")
    torch.set_num_threads(args.threads)
    points = torch.from_numpy(np.fromfile(args.scan, dtype=np.float32).reshape(-1, 4))

    load_before = os.getloadavg()[0]
    rows = run(points, args)
    print_table(rows, args, len(points), load_before)
    slowest = min(row["project_scans_per_s"] for row in rows)
    print(f"goal >= 50 scans/s projection: {'met' if slowest >= 50 else 'NOT met'} (slowest {slowest:.1f})")
    atomic_write_json(
        args.out,
        {
            "benchmark": "range_view",
            "scan": str(args.scan),
            "points": len(points),
            "threads": args.threads,
            "load_average_1min_before": load_before,
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(default)"),
            "machine": host_info(),
            "quick": args.quick,
            "results": rows,
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
