"""Seconds to score 1,000 scans with each generation metric (BEV JSD/MMD, FD/KID, TTCE, CTC) on this machine.

    python benchmarks/bench_metrics.py            # full: includes scipy sqrtm on 4096-D (~3 min on 2 cores)
    python benchmarks/bench_metrics.py --quick    # 1 repetition, no 4096-D sqrtm, no full-resolution ICP

Measured directly: BEV histograms of 1,000 scans (the 6 real SemanticKITTI seq-00 frames cycled), JSD and
MMD on 1,000 vs 1,000 histograms, FD and polynomial MMD (KID) on 1,000 vs 1,000 random features of 4096-D
(FRD) and 1808-D (FPD). Extrapolated (marked "x"): TTCE and CTC are timed per pair on the real frames 0-5
(all pairs of their intervals, tree/cloud building included) and multiplied by the pairs of one 1,000-frame
sequence (TTCE k=3,4: 1,993 pairs; CTC k=1..4: 3,990 pairs). Medians over repetitions.
Writes benchmarks/results/speed/metrics.json. The machine is shared: the load average is recorded with the figures.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json
from u4d_aug.metrics.bev import MMD_REPORT_SCALE, bev_histogram, bev_jsd, bev_mmd
from u4d_aug.metrics.frechet import frechet_from_features, polynomial_mmd
from u4d_aug.metrics.temporal import CTC_INTERVALS, TTCE_INTERVALS, ctc, load_kitti_sequence, ttce

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = REPO.parent / "shared" / "data" / "real" / "semantickitti" / "sequences" / "00"
NUM_SCANS = 1000


def timed(function: Callable[[], Any], reps: int) -> tuple[float, Any]:
    """Median seconds of `reps` calls and the last result."""
    times, result = [], None
    for _ in range(reps):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def num_pairs(num_frames: int, intervals: tuple[int, ...]) -> int:
    """Pairs (i, i + k) of one sequence of `num_frames` frames over the intervals."""
    return sum(max(num_frames - k, 0) for k in intervals)


def bench_bev(scans: list[np.ndarray], reps: int, rng: np.random.Generator) -> list[dict]:
    """Histogram 1,000 scans; JSD and MMD of 1,000 vs 1,000 histograms (real ones with Poisson jitter)."""
    rows = []
    cycle = [scans[i % len(scans)] for i in range(NUM_SCANS)]
    seconds, _ = timed(lambda: [bev_histogram(points) for points in cycle], reps)
    rows.append({"metric": "BEV histogram", "case": "1000 real scans", "seconds": seconds, "how": "measured"})
    base = np.stack([bev_histogram(points) for points in scans])  # (6, 100, 100)
    hists_a = rng.poisson(base[rng.integers(0, len(scans), NUM_SCANS)]).astype(np.float32)
    hists_b = rng.poisson(base[rng.integers(0, len(scans), NUM_SCANS)]).astype(np.float32)
    seconds, value = timed(lambda: bev_jsd(hists_a, hists_b), reps)
    rows.append({"metric": "BEV JSD", "case": "1k vs 1k hists", "seconds": seconds, "how": "measured", "value": value})
    seconds, value = timed(lambda: bev_mmd(hists_a, hists_b), reps)
    rows.append(
        {
            "metric": "BEV MMD",
            "case": "1k vs 1k hists",
            "seconds": seconds,
            "how": "measured",
            "value": value,
            "value_x1e4": value * MMD_REPORT_SCALE,
        }
    )
    return rows


def bench_frechet(reps: int, quick: bool, rng: np.random.Generator) -> list[dict]:
    """FD (both trace methods) and KID on 1,000 vs 1,000 random features; the methods' values side by side."""
    rows = []
    for dim in (4096, 1808):
        f1 = rng.standard_normal((NUM_SCANS, dim))
        f2 = rng.standard_normal((NUM_SCANS, dim)) + 0.05
        seconds_gram, value_gram = timed(functools.partial(frechet_from_features, f1, f2, method="gram"), reps)
        rows.append(
            {
                "metric": f"FD {dim}-D",
                "case": "gram (default)",
                "seconds": seconds_gram,
                "how": "measured",
                "value": value_gram,
            }
        )
        if dim == 4096 and quick:
            rows.append({"metric": f"FD {dim}-D", "case": "scipy sqrtm", "seconds": None, "how": "skipped (--quick)"})
        else:
            # One repetition only: a (4096, 4096) Schur decomposition takes minutes.
            seconds, value = timed(functools.partial(frechet_from_features, f1, f2, method="sqrtm"), 1)
            rows.append(
                {
                    "metric": f"FD {dim}-D",
                    "case": "scipy sqrtm",
                    "seconds": seconds,
                    "how": "measured (1 rep)",
                    "value": value,
                    "relative_difference_vs_gram": abs(value - value_gram) / abs(value),
                    "slowdown_vs_gram": seconds / seconds_gram,
                }
            )
        seconds, value = timed(functools.partial(polynomial_mmd, f1, f2, np.random.default_rng(0)), reps)
        rows.append(
            {
                "metric": f"KID {dim}-D",
                "case": "100 subsets of 1000",
                "seconds": seconds,
                "how": "measured",
                "value": value,
            }
        )
    return rows


def bench_temporal(scans: list[np.ndarray], poses: np.ndarray, reps: int, quick: bool) -> list[dict]:
    """TTCE and CTC timed per pair on the real frames, extrapolated to a 1,000-frame sequence."""
    rows = []
    variants: list[tuple[str, float | None]] = [("voxel 0.2 m (default)", 0.2)]
    if not quick:
        variants.append(("full resolution (LC)", None))
    for case, voxel_size in variants:
        pairs = num_pairs(len(scans), TTCE_INTERVALS)
        seconds, scores = timed(
            functools.partial(ttce, scans, poses, voxel_size=voxel_size), 1 if voxel_size is None else reps
        )
        total_pairs = num_pairs(NUM_SCANS, TTCE_INTERVALS)
        rows.append(
            {
                "metric": "TTCE k=3,4",
                "case": case,
                "seconds": seconds / pairs * total_pairs,
                "how": f"x {total_pairs} pairs",
                "seconds_per_pair": seconds / pairs,
                "value": scores.mean,
            }
        )
    pairs = num_pairs(len(scans), CTC_INTERVALS)
    seconds, scores = timed(lambda: ctc(scans, poses), reps)
    total_pairs = num_pairs(NUM_SCANS, CTC_INTERVALS)
    rows.append(
        {
            "metric": "CTC k=1..4",
            "case": "cKDTree, 1 worker",
            "seconds": seconds / pairs * total_pairs,
            "how": f"x {total_pairs} pairs",
            "seconds_per_pair": seconds / pairs,
            "value": scores.mean,
        }
    )
    return rows


def _format_value(value: Any) -> str:
    if isinstance(value, dict):
        return " ".join(f"{k}:{v:.4g}" for k, v in value.items())
    return "" if value is None else f"{value:.6g}"


def print_table(rows: list[dict]) -> None:
    header = f"{'metric':<14} {'case':<22} {'s / 1000 scans':>14}  {'how':<18} value"
    print(header)
    print("-" * len(header))
    for row in rows:
        seconds = "-" if row["seconds"] is None else f"{row['seconds']:.2f}"
        print(
            f"{row['metric']:<14} {row['case']:<22} {seconds:>14}  {row['how']:<18} {_format_value(row.get('value'))}"
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE, help="SemanticKITTI sequence folder")
    parser.add_argument("--reps", type=int, default=3, help="repetitions of the fast measures; the median is reported")
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    parser.add_argument("--quick", action="store_true", help="1 repetition, skip 4096-D sqrtm and full-resolution ICP")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "speed" / "metrics.json")
    args = parser.parse_args()
    if args.quick:
        args.reps = 1
    if not (args.sequence / "velodyne").is_dir():
        parser.error(f"sequence not found: {args.sequence} (the real scans live in ../shared/data/real)")
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    scans, poses = load_kitti_sequence(args.sequence)

    load_before = os.getloadavg()[0]
    rows = bench_bev(scans, args.reps, rng)
    rows += bench_frechet(args.reps, args.quick, rng)
    rows += bench_temporal(scans, poses, args.reps, args.quick)
    print(f"metrics on {args.sequence} ({len(scans)} real frames), torch {torch.__version__}, {args.threads} threads")
    print(f"load average before {load_before:.2f}, after {os.getloadavg()[0]:.2f}; 'x N pairs' rows are extrapolated")
    print_table(rows)
    atomic_write_json(
        args.out,
        {
            "benchmark": "metrics",
            "num_scans": NUM_SCANS,
            "sequence": str(args.sequence),
            "real_frames": len(scans),
            "threads": args.threads,
            "load_average_1min_before": load_before,
            "machine": host_info(),
            "quick": args.quick,
            "reps": args.reps,
            "results": rows,
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
