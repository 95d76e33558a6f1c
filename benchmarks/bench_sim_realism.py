"""Simulated-world realism over seeds: `u4d sim-report` figures of several simulated worlds against the real scans.

One world per seed (a SimConfig preset, HDL-64E, `--sequences` places x `--frames` frames, as `u4d simulate
--sequences N --frames F --seed S --config PRESET`), each compared with ../shared/data/real/semantickitti by
`u4d_aug.data.sim.report.compare` (30 evenly spaced simulated scans vs the real ones): range-histogram JS distance (1 m
bins, 0-80 m; the goal is <= 0.10), elevation JS, points per scan, range shares, the range JS of one simulated
place (6 consecutive scans) against its own pool (the spread a 6-frame reference of one place carries), the 1 m bins
that add most to the mean JS divergence, the per-class remission JS distance (labelled returns within 50 m, the real
seq-00 frames 0-2), the range roughness and the mixed-pixel share of depth edges. Writes
benchmarks/results/world/<name>.json, <name>.md and <name>_remission.png (the per-class remission histograms of all
seeds pooled against the real ones); `--table NAME ...` writes one markdown table over several such json files.

    python benchmarks/bench_sim_realism.py [--seeds 0 1 2 3] [--config sim/varied] [--set key=value ...] [--name N]
    python benchmarks/bench_sim_realism.py --table sim_realism_default sim_realism_varied --name sim_realism
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

from u4d_aug.config import config_to_dict, load_config
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.report import compare, dataset_stats, edge_summary, intensity_distances, plot_intensity
from u4d_aug.data.sim.writer import simulate
from u4d_aug.io import atomic_write_json, atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "world"
# ../shared/data/real beside the checkout; U4D_REAL_DATA points elsewhere (a git worktree one folder deeper)
REAL = Path(os.environ.get("U4D_REAL_DATA") or ROOT.parent / "shared" / "data" / "real") / "semantickitti"


def bin_divergence(p_counts: np.ndarray, q_counts: np.ndarray) -> np.ndarray:
    """Per-bin terms of the JS divergence (base 2) of two histograms; they sum to JS distance squared."""
    p, q = p_counts / p_counts.sum(), q_counts / q_counts.sum()
    m = (p + q) / 2
    terms = np.zeros_like(p)
    for x in (p, q):
        nz = x > 0
        terms[nz] += 0.5 * x[nz] * np.log2(x[nz] / m[nz])
    return terms


def _mean(rows: list[dict], key: str) -> float | None:
    values = [r[key] for r in rows if r.get(key) is not None]
    return statistics.fmean(values) if values else None


def run(args: argparse.Namespace) -> int:
    """Simulate one world per seed, compare each with the real scans, write <name>.json / .md / _remission.png."""
    if not (args.real / "sequences").is_dir():
        print(f"no real SemanticKITTI scans at {args.real} (expected sequences/XX/velodyne)", file=sys.stderr)
        return 1
    cfg = load_config(SimConfig, args.config, args.set)
    work = args.work or Path(tempfile.mkdtemp(prefix="u4d_realism_"))
    real = dataset_stats(args.real)
    rows, divergence, shares = [], [], []
    pooled = None
    for seed in args.seeds:
        root = work / f"seed{seed}"
        simulate(root, args.sequences, args.frames, seed, workers=1, config=cfg, progress=False)
        report, sim, _ = compare(root, args.real)
        types = json.loads((root / "manifest.json").read_text())["street_types"]
        if args.work is None:
            shutil.rmtree(root)
        divergence.append(bin_divergence(sim["range_hist"], real["range_hist"]))
        shares.append(sim["range_hist"] / sim["range_hist"].sum())
        pooled = sim["intensity_hist"] + (0 if pooled is None else pooled)
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
                "remission_js_mean": report["intensity_js"]["mean"],
                "remission_js_weighted": report["intensity_js"]["weighted"],
                "remission_js": report["intensity_js"]["per_class"],
                "zero_share": {k: v["sim"] for k, v in report["intensity_js"]["zero_share"].items()},
                "edges": report["edges"]["sim"],
                "street_types": types,
            }
        )
        print(
            f"seed {seed}: range JS {report['range_js']:.3f}, remission JS {report['intensity_js']['mean']:.3f}",
            flush=True,
        )
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    mean_terms = np.mean(divergence, axis=0)
    real_share = real["range_hist"] / real["range_hist"].sum()
    sim_share = np.mean(shares, axis=0)
    top = np.argsort(mean_terms)[::-1][:8]
    classes = sorted({name for r in rows for name in r["remission_js"]})
    pooled_report = {"intensity_js": intensity_distances(pooled, real["intensity_hist"])}
    summary = {
        "range_js_mean": _mean(rows, "range_js"),
        "range_js_min": min(r["range_js"] for r in rows),
        "range_js_max": max(r["range_js"] for r in rows),
        "seeds_within_goal": sum(r["range_js"] <= 0.10 for r in rows),
        "elevation_js_mean": _mean(rows, "elevation_js"),
        "points_per_scan_mean": _mean(rows, "points_per_scan"),
        "place_spread_median_mean": _mean(rows, "place_spread_median"),
        "remission_js_mean": _mean(rows, "remission_js_mean"),
        "remission_js_weighted_mean": _mean(rows, "remission_js_weighted"),
        "remission_js_per_class_mean": {
            name: statistics.fmean(r["remission_js"][name] for r in rows if name in r["remission_js"])
            for name in classes
        },
        "remission_js_pooled": pooled_report["intensity_js"],
        "roughness_mm_mean": statistics.fmean(r["edges"]["roughness_median_mm"] for r in rows),
        "mixed_share_of_edges_mean": statistics.fmean(r["edges"]["mixed_share_of_edges"] for r in rows),
        "real": {
            "points_per_scan": float(real["points_per_scan"]),
            "edges": edge_summary(real),
            "zero_share": {k: v["real"] for k, v in pooled_report["intensity_js"]["zero_share"].items()},
        },
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
    result = {
        "name": args.name,
        "command": "python " + " ".join(sys.argv),
        "config": args.config,
        "overrides": args.set,
        "sequences": args.sequences,
        "frames": args.frames,
        "real": str(args.real),
        "resolved_config": config_to_dict(cfg),
        "seeds": rows,
        **summary,
    }
    _print(result)
    path = RESULTS / f"{args.name}.json"
    atomic_write_json(path, result)
    png = plot_intensity(
        RESULTS / f"{args.name}_remission.png",
        pooled_report,
        {"intensity_hist": pooled},
        {"intensity_hist": real["intensity_hist"]},
    )
    print(f"wrote {path} and {png}")
    return 0


def _print(result: dict) -> None:
    rows = result["seeds"]
    print()
    print(f"{'seed':>4} {'range JS':>9} {'elev JS':>8} {'pts/scan':>9} {'remission JS':>13} {'place spread':>13}")
    for r in rows:
        print(
            f"{r['seed']:>4} {r['range_js']:>9.3f} {r['elevation_js']:>8.3f} {r['points_per_scan']:>9.0f} "
            f"{r['remission_js_mean']:>13.3f} {r['place_spread_median'] or float('nan'):>13.3f}"
        )
    print(
        f"mean range JS {result['range_js_mean']:.3f} (min {result['range_js_min']:.3f}, max "
        f"{result['range_js_max']:.3f}); {result['seeds_within_goal']}/{len(rows)} seeds <= 0.10; remission JS mean "
        f"{result['remission_js_mean']:.3f} (weighted {result['remission_js_weighted_mean']:.3f}); roughness "
        f"{result['roughness_mm_mean']:.1f} mm (real {result['real']['edges']['roughness_median_mm']:.1f}); mixed "
        f"{result['mixed_share_of_edges_mean']:.3f} (real {result['real']['edges']['mixed_share_of_edges']:.3f})"
    )
    print("bins adding most to the JS divergence (mean over seeds; total = JS distance squared):")
    for b in result["top_bins"]:
        print(
            f"  {b['bin_m'][0]:>2}-{b['bin_m'][1]:<2} m  sim {100 * b['sim_share']:5.2f} %  real "
            f"{100 * b['real_share']:5.2f} %  divergence {b['divergence']:.4f}"
        )


def table(names: list[str], out: str) -> int:
    """One markdown table (and the per-class remission JS) over several result json files of this benchmark."""
    results = [json.loads((RESULTS / f"{name}.json").read_text()) for name in names]
    lines = [
        "| world | places x frames x seeds | range JS mean (min-max) | seeds <= 0.10 | elevation JS | points/scan | "
        "remission JS mean (weighted) | roughness mm | mixed share of edges |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| `{r['name']}` | {r['sequences']} x {r['frames']} x {len(r['seeds'])} | {r['range_js_mean']:.3f} "
            f"({r['range_js_min']:.3f}-{r['range_js_max']:.3f}) | {r['seeds_within_goal']}/{len(r['seeds'])} | "
            f"{r['elevation_js_mean']:.3f} | {r['points_per_scan_mean']:.0f} | {r['remission_js_mean']:.3f} "
            f"({r['remission_js_weighted_mean']:.3f}) | {r['roughness_mm_mean']:.1f} | "
            f"{r['mixed_share_of_edges_mean']:.3f} |"
        )
    real = results[0]["real"]
    lines.append(
        f"| real seq 00 (frames 0-5; labels 0-2) | | | | | {real['points_per_scan']:.0f} | | "
        f"{real['edges']['roughness_median_mm']:.1f} | {real['edges']['mixed_share_of_edges']:.3f} |"
    )
    classes = sorted({c for r in results for c in r["remission_js_per_class_mean"]})
    header = " | ".join(f"`{r['name']}`" for r in results)
    lines += ["", "Remission JS distance per class (mean over seeds):", "", f"| class | {header} |"]
    lines.append("|---|" + "---|" * len(results))
    for c in classes:
        cells = [r["remission_js_per_class_mean"].get(c) for r in results]
        lines.append(f"| {c} | " + " | ".join("-" if v is None else f"{v:.3f}" for v in cells) + " |")
    lines += ["", "Share of returns reading 0 per class (seeds pooled):", "", f"| class | {header} | real |"]
    lines.append("|---|" + "---|" * (len(results) + 1))
    for c in classes:
        cells = [r["remission_js_pooled"]["zero_share"].get(c, {}).get("sim") for r in results]
        cells.append(results[0]["real"]["zero_share"].get(c))
        lines.append(f"| {c} | " + " | ".join("-" if v is None else f"{v:.2f}" for v in cells) + " |")
    commands = [r["command"] if r["command"].startswith("python") else f"python {r['command']}" for r in results]
    lines += ["", "Commands:", ""] + [f"- `{r['name']}`: `{c}`" for r, c in zip(results, commands)]
    path = RESULTS / f"{out}_table.md"
    atomic_write_text(path, "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {path}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--sequences", type=int, default=8)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--config", default=None, help="SimConfig preset or yaml (default: the default world)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    parser.add_argument("--name", default="sim_realism", help="result file stem under benchmarks/results/world/")
    parser.add_argument("--work", type=Path, default=None, help="keep the worlds here (reused when present)")
    parser.add_argument("--real", type=Path, default=REAL)
    parser.add_argument("--table", nargs="+", default=None, metavar="NAME", help="tabulate earlier results only")
    args = parser.parse_args()
    if args.table:
        return table(args.table, args.name)
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
