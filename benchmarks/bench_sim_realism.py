"""Simulated-world realism over seeds: `u4d sim-report` figures of several default worlds against the real scans.

One world per seed (default config, HDL-64E, 8 places x 30 frames, as `u4d simulate --sequences 8 --frames 30
--seed S`), each compared with ../shared/data/real/semantickitti by `u4d_aug.data.sim.report.compare` (30 evenly
spaced simulated scans vs the real ones): range-histogram JS distance (1 m bins, 0-80 m; the issue's goal is
<= 0.10), elevation JS, points per scan, range shares, and the range JS of one simulated place (6 consecutive
scans) against its own pool, the spread a 6-frame reference of one place carries. Also the 1 m bins that add
most to the mean JS divergence. Writes benchmarks/results/sim_realism.json.

    python benchmarks/bench_sim_realism.py [--seeds 0 1 2 3] [--work DIR]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

from u4d_aug.data.sim.report import compare, dataset_stats
from u4d_aug.data.sim.writer import simulate
from u4d_aug.io import atomic_write_json

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "sim_realism.json"
REAL = ROOT.parent / "shared" / "data" / "real" / "semantickitti"


def bin_divergence(p_counts: np.ndarray, q_counts: np.ndarray) -> np.ndarray:
    """Per-bin terms of the JS divergence (base 2) of two histograms; they sum to JS distance squared."""
    p, q = p_counts / p_counts.sum(), q_counts / q_counts.sum()
    m = (p + q) / 2
    terms = np.zeros_like(p)
    for x in (p, q):
        nz = x > 0
        terms[nz] += 0.5 * x[nz] * np.log2(x[nz] / m[nz])
    return terms


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--sequences", type=int, default=8)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--work", type=Path, default=None, help="keep the worlds here (reused when present)")
    parser.add_argument("--real", type=Path, default=REAL)
    args = parser.parse_args()
    if not (args.real / "sequences").is_dir():
        print(f"no real SemanticKITTI scans at {args.real} (expected sequences/XX/velodyne)", file=sys.stderr)
        return 1
    work = args.work or Path(tempfile.mkdtemp(prefix="u4d_realism_"))
    real = dataset_stats(args.real)
    rows, divergence, shares = [], [], []
    for seed in args.seeds:
        root = work / f"seed{seed}"
        simulate(root, args.sequences, args.frames, seed, workers=1, progress=False)
        report, sim, _ = compare(root, args.real)
        divergence.append(bin_divergence(sim["range_hist"], real["range_hist"]))
        shares.append(sim["range_hist"] / sim["range_hist"].sum())
        spread = report["range_js_place_spread"]
        rows.append(
            {
                "seed": seed,
                "range_js": report["range_js"],
                "elevation_js": report["elevation_js"],
                "points_per_scan": report["points_per_scan"]["sim"],
                "place_spread_median": spread["median"],
                "place_spread_min": spread["min"],
                "place_spread_max": spread["max"],
                "range_share": {k: v["sim"] for k, v in report["range_share"].items()},
            }
        )
        print(f"seed {seed}: range JS {report['range_js']:.3f}", flush=True)
    mean_terms = np.mean(divergence, axis=0)
    real_share = real["range_hist"] / real["range_hist"].sum()
    sim_share = np.mean(shares, axis=0)
    top = np.argsort(mean_terms)[::-1][:8]
    summary = {
        "range_js_mean": statistics.fmean(r["range_js"] for r in rows),
        "range_js_min": min(r["range_js"] for r in rows),
        "range_js_max": max(r["range_js"] for r in rows),
        "seeds_within_goal": sum(r["range_js"] <= 0.10 for r in rows),
        "place_spread_median_mean": statistics.fmean(r["place_spread_median"] for r in rows),
        "real_points_per_scan": float(real["points_per_scan"]),
        "top_bins": [
            {
                "bin_m": [int(i), int(i) + 1],
                "sim_share": float(sim_share[i]),
                "real_share": float(real_share[i]),
                "divergence": float(mean_terms[i]),
            }
            for i in top
        ],
    }
    print()
    print(f"{'seed':>4} {'range JS':>9} {'elev JS':>8} {'pts/scan':>9} {'place spread med (min-max)':>28}")
    for r in rows:
        spread = f"{r['place_spread_median']:.3f} ({r['place_spread_min']:.3f}-{r['place_spread_max']:.3f})"
        print(
            f"{r['seed']:>4} {r['range_js']:>9.3f} {r['elevation_js']:>8.3f} {r['points_per_scan']:>9.0f} {spread:>28}"
        )
    print(
        f"mean range JS {summary['range_js_mean']:.3f} (min {summary['range_js_min']:.3f}, max "
        f"{summary['range_js_max']:.3f}); {summary['seeds_within_goal']}/{len(rows)} seeds <= 0.10; "
        f"real points/scan {summary['real_points_per_scan']:.0f}"
    )
    print("bins adding most to the JS divergence (mean over seeds; total = JS distance squared):")
    for b in summary["top_bins"]:
        print(
            f"  {b['bin_m'][0]:>2}-{b['bin_m'][1]:<2} m  sim {100 * b['sim_share']:5.2f} %  real "
            f"{100 * b['real_share']:5.2f} %  divergence {b['divergence']:.4f}"
        )
    atomic_write_json(
        RESULTS,
        {"sequences": args.sequences, "frames": args.frames, "real": str(args.real), "seeds": rows, **summary},
    )
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
