"""Simulated-world realism per real scan source: each preset's worlds against every real source in ../shared/data/real.

`bench_sim_realism.py` measures worlds against the six SemanticKITTI seq-00 frames pooled; this script keeps the
sources apart (../shared/data/real/SOURCES.md): seq 00 frames 000000-000002 (labelled), seq 00 frames 000003-000005
(unlabelled), and the full nuScenes LIDAR_TOP keyframe (HDL-32E, read as the project reads nuScenes:
`read_nuscenes_scan`, intensity / 255, the returns within 1 m of the sensor dropped as the devkit's `remove_close`
does, points put ring-major by their ring column). Folders whose scans are excerpts of fewer than MIN_SCAN_POINTS
points (the mmdetection3d test files) are listed as skipped, and sources the issue names but the folder lacks (KITTI
object, `training/velodyne`) as absent.

One world per preset and seed (`u4d simulate --config sim/PRESET --seed S --sequences P --frames F`, the HDL-64E for
seg_rich and varied, the HDL-32E for nuscenes: the scans `--format nuscenes` writes, before its 90 deg turn of the
frame), ray-cast in memory on one thread: no world is written to disk. Per (world, source), with
`u4d_aug.data.sim.report` (`frames_stats`, `edge_summary`, `intensity_distances`):
range-histogram JS distance (1 m bins 0-80 m), elevation JS (0.5 deg bins over -32..+12 deg, wide enough for both
sensors; the HDL-32E's rings lie 1.33 deg apart, so its histogram is a row of spikes and a ring shifted by 0.25 deg
moves between bins), the JS of the points per ring (top ring first: rings lost to the sky or hidden by the ego car),
points per scan, the JS of the remission of every return (INTENSITY_BINS: a bin for 0, then 0.05 steps),
the per-class remission JS mean and real-share-weighted mean (labelled sources, returns within 50 m), the range
roughness and the mixed-pixel share of depth edges. All JS are distances in base 2: 0 = identical, 1 = disjoint. The
main table pairs a world with the sources of its own sensor; other pairs (and real sources against each other) are in
the json and a second table. Writes benchmarks/results/world/<name>.json, <name>.md and <name>_remission.png.

    python benchmarks/bench_sim_realism_sources.py [--seeds 0 1] [--sequences 12] [--frames 3] [--name N]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial.distance import jensenshannon

from u4d_aug.config import config_to_dict, load_config
from u4d_aug.data.formats import load_kitti_frame, read_nuscenes_scan
from u4d_aug.data.sensors import get_sensor
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.report import INTENSITY_BINS, edge_summary, frames_stats, intensity_distances
from u4d_aug.data.sim.writer import build_sequence, render_frame
from u4d_aug.io import atomic_write_json, atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "world"
# ../shared/data/real beside the checkout; U4D_REAL_DATA points elsewhere (a git worktree one folder deeper)
REAL = Path(os.environ.get("U4D_REAL_DATA") or ROOT.parent / "shared" / "data" / "real")
PRESETS = {
    "seg_rich": ("sim/seg_rich", "hdl64"),
    "varied": ("sim/varied", "hdl64"),
    "nuscenes": ("sim/nuscenes", "hdl32"),
}
SENSOR_NAMES = {"hdl64": "HDL-64E", "hdl32": "HDL-32E"}
ELEVATION_BINS = np.arange(-32.0, 12.01, 0.5)  # degrees: HDL-64E (+4..-25) and HDL-32E (+10.7..-30.7) alike
MIN_SCAN_POINTS = 10_000  # a source whose largest scan holds fewer points is an excerpt, too small for histograms
COLUMNS = {"kitti": 4, "nuscenes": 5}  # float32 columns of a .bin / .pcd.bin
METRICS = (  # (key, table header, format)
    ("range_js", "range JS", ".3f"),
    ("elevation_js", "elev. JS", ".3f"),
    ("ring_js", "ring JS", ".3f"),
    ("intensity_js", "remission JS", ".3f"),
    ("class_intensity_js", "class rem. JS", ".3f"),
    ("points_per_scan", "pts/scan", ".0f"),
    ("mixed_share", "mixed", ".3f"),
    ("roughness_mm", "rough. mm", ".1f"),
)


class Source(NamedTuple):
    """One real scan source: its scans (and labels) in one file format from one sensor."""

    name: str
    description: str
    kind: str  # kitti | nuscenes (file format)
    sensor: str  # hdl64 | hdl32
    scans: tuple[Path, ...]
    labels: tuple[Path | None, ...]

    @property
    def labelled(self) -> bool:
        return any(label is not None for label in self.labels)


def _points_in(path: Path, kind: str) -> int:
    return path.stat().st_size // (4 * COLUMNS[kind])


def _kitti_sources(folder: Path) -> Iterator[Source]:
    """SemanticKITTI-layout scans of a folder, one source per sequence and per labelled / unlabelled frames."""
    for velodyne in sorted(folder.glob("sequences/*/velodyne")):
        scans = sorted(velodyne.glob("*.bin"))
        labels = [velodyne.parent / "labels" / f"{scan.stem}.label" for scan in scans]
        for labelled in (True, False):
            chosen = [(s, lab) for s, lab in zip(scans, labels) if lab.is_file() == labelled]
            if not chosen:
                continue
            which = "labelled" if labelled else "unlabelled"
            yield Source(
                name=f"{folder.name}_{velodyne.parent.name}_{which}",
                description=f"{folder.name} seq {velodyne.parent.name} frames {chosen[0][0].stem}-{chosen[-1][0].stem} "
                f"({which}, HDL-64E)",
                kind="kitti",
                sensor="hdl64",
                scans=tuple(s for s, _ in chosen),
                labels=tuple(lab if labelled else None for _, lab in chosen),
            )


def find_sources(real: Path) -> tuple[list[Source], list[dict]]:
    """(usable sources, skipped or absent ones with a reason) of a real-data folder laid out as SOURCES.md says."""
    candidates, skipped, found_object = [], [], False
    for folder in sorted(p for p in real.iterdir() if p.is_dir()):
        candidates += list(_kitti_sources(folder))
        nuscenes = sorted(folder.glob("**/LIDAR_TOP/*.pcd.bin"))
        if nuscenes:
            description = f"{folder.name} LIDAR_TOP (HDL-32E)"
            candidates.append(
                Source(folder.name, description, "nuscenes", "hdl32", tuple(nuscenes), (None,) * len(nuscenes))
            )
        kitti_object = sorted(folder.glob("**/training/velodyne/*.bin"))
        if kitti_object:
            found_object = True
            description = f"{folder.name} KITTI object training scans (HDL-64E)"
            candidates.append(
                Source(
                    f"{folder.name}_object",
                    description,
                    "kitti",
                    "hdl64",
                    tuple(kitti_object),
                    (None,) * len(kitti_object),
                )
            )
    sources = []
    for source in candidates:
        counts = [_points_in(scan, source.kind) for scan in source.scans]
        if max(counts) < MIN_SCAN_POINTS:
            skipped.append(
                {
                    "name": source.name,
                    "status": "skipped",
                    "reason": f"excerpts of {', '.join(map(str, counts))} points per scan (< {MIN_SCAN_POINTS}): "
                    "too few for range, elevation and remission distributions",
                }
            )
        else:
            sources.append(source)
    if not found_object:
        skipped.append(
            {
                "name": "kitti_object",
                "status": "absent",
                "reason": f"named in the issue, but {real} holds no KITTI object scans (no training/velodyne/*.bin)",
            }
        )
    return sources, skipped


def source_frames(source: Source) -> Iterator[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """(points with remission in [0, 1], raw semantic ids or None, ring or None) of each scan of a real source."""
    for scan, label in zip(source.scans, source.labels):
        if source.kind == "kitti":
            frame = load_kitti_frame(scan, label)
            yield frame.points, frame.semantic, None  # KITTI stores one ring after the other: rings from the order
        else:
            nuscenes = read_nuscenes_scan(scan)  # intensity / 255, returns within 1 m (the ego car) dropped
            ring = get_sensor(source.sensor).num_rings - 1 - nuscenes.ring  # top ring first, as KITTI stores them
            order = np.argsort(ring, kind="stable")  # ring-major; the firing order keeps each ring in azimuth order
            yield nuscenes.points[order], None, ring[order]


def world_frames(
    cfg: SimConfig, sensor: str, seed: int, sequences: int, frames: int
) -> Iterator[tuple[np.ndarray, np.ndarray, None]]:
    """The scans `u4d simulate --seed seed --sequences sequences --frames frames` writes, ray-cast on one thread."""
    for index in range(sequences):
        seq = build_sequence(seed, index, frames, get_sensor(sensor), cfg, nthreads=1)
        for frame in range(frames):
            scan = render_frame(seq, frame)
            yield scan.points, scan.semantic, None


def distances(sim: dict, real: dict) -> dict:
    """Sensor and surface figures of one dataset (`frames_stats`) against another: JS distances (base 2), the
    per-class remission JS where both are labelled, points per scan and edge statistics of each."""
    both_labelled = "intensity_hist" in sim and "intensity_hist" in real
    classes = intensity_distances(sim["intensity_hist"], real["intensity_hist"]) if both_labelled else None
    return {
        "range_js": float(jensenshannon(sim["range_hist"], real["range_hist"], base=2)),
        "elevation_js": float(jensenshannon(sim["elevation_hist"], real["elevation_hist"], base=2)),
        "ring_js": float(jensenshannon(sim["ring_counts"], real["ring_counts"], base=2)),
        "intensity_js": float(jensenshannon(sim["intensity_all"], real["intensity_all"], base=2)),
        "class_intensity_js": classes["mean"] if classes else None,
        "class_intensity_js_weighted": classes["weighted"] if classes else None,
        "class_intensity_js_per_class": classes["per_class"] if classes else None,
        "points_per_scan": {"sim": sim["points_per_scan"], "real": real["points_per_scan"]},
        "edges": {"sim": edge_summary(sim), "real": edge_summary(real)},
    }


def scalars(pair: dict) -> dict[str, float | None]:
    """The per-seed metrics of one `distances` result (points, mixed share and roughness of the simulated side)."""
    return {
        "range_js": pair["range_js"],
        "elevation_js": pair["elevation_js"],
        "ring_js": pair["ring_js"],
        "intensity_js": pair["intensity_js"],
        "class_intensity_js": pair["class_intensity_js"],
        "class_intensity_js_weighted": pair["class_intensity_js_weighted"],
        "points_per_scan": pair["points_per_scan"]["sim"],
        "mixed_share": pair["edges"]["sim"]["mixed_share_of_edges"],
        "roughness_mm": pair["edges"]["sim"]["roughness_median_mm"],
    }


def mean_std(values: list[float | None]) -> dict | None:
    """{"mean", "std", "n"} over the seeds (std with n - 1; 0 for one seed), None when no seed has a value."""
    kept = [v for v in values if v is not None]
    if not kept:
        return None
    return {"mean": statistics.fmean(kept), "std": statistics.stdev(kept) if len(kept) > 1 else 0.0, "n": len(kept)}


def measure(
    sources: list[Source], presets: dict[str, tuple[str, str]], seeds: list[int], sequences: int, frames: int
) -> dict:
    """Every preset's world per seed against every source, and the sources against each other."""
    real = {s.name: frames_stats(source_frames(s), ELEVATION_BINS) for s in sources}
    result: dict = {"real": {}, "worlds": {}, "real_vs_real": {}}
    for s in sources:
        result["real"][s.name] = {
            "description": s.description,
            "sensor": s.sensor,
            "scans": [str(p) for p in s.scans],
            "labelled": s.labelled,
            "frames": real[s.name]["frames"],
            "points_per_scan": real[s.name]["points_per_scan"],
            "edges": edge_summary(real[s.name]),
            "intensity_hist": real[s.name]["intensity_all"].tolist(),
        }
        result["real_vs_real"][s.name] = {o.name: distances(real[s.name], real[o.name]) for o in sources}
    for preset, (config, sensor) in presets.items():
        cfg = load_config(SimConfig, config)
        per_seed, pooled = [], 0
        for seed in seeds:
            start = time.perf_counter()
            sim = frames_stats(world_frames(cfg, sensor, seed, sequences, frames), ELEVATION_BINS)
            pairs = {s.name: distances(sim, real[s.name]) for s in sources}
            per_seed.append({"seed": seed, "seconds": time.perf_counter() - start, "sources": pairs})
            pooled = pooled + sim["intensity_all"]
            same = [s.name for s in sources if s.sensor == sensor]
            ranges = ", ".join(f"{name} range JS {pairs[name]['range_js']:.3f}" for name in same)
            print(f"{preset} seed {seed}: {ranges} ({per_seed[-1]['seconds']:.0f} s)", flush=True)
        summary = {
            s.name: {
                key: mean_std([scalars(r["sources"][s.name])[key] for r in per_seed])
                for key in scalars(per_seed[0]["sources"][s.name])
            }
            | {"same_sensor": s.sensor == sensor}
            for s in sources
        }
        result["worlds"][preset] = {
            "config": config,
            "sensor": sensor,
            "resolved_config": config_to_dict(cfg),
            "seeds": per_seed,
            "summary": summary,
            "intensity_hist_pooled": np.asarray(pooled).tolist(),
        }
    return result


def _cell(stat: dict | None, fmt: str) -> str:
    if stat is None:
        return "-"
    if stat["n"] < 2:
        return format(stat["mean"], fmt)
    return f"{format(stat['mean'], fmt)} ± {format(stat['std'], fmt)}"


def markdown(result: dict) -> str:
    """The tables: worlds x (sources x metrics) for same-sensor pairs, the real reference row, cross pairs."""
    sources = list(result["real"])
    seeds = result["seeds"]
    columns = [(s, key, head, fmt) for s in sources for key, head, fmt in METRICS]
    columns = [c for c in columns if c[1] != "class_intensity_js" or result["real"][c[0]]["labelled"]]
    short = {s: f"S{k + 1}" for k, s in enumerate(sources)}
    lines = [
        f"# Simulated-world realism per real source ({result['sequences']} places x {result['frames']} frames, "
        f"seeds {', '.join(map(str, seeds))})",
        "",
        "Sources (folders of ../shared/data/real, see its SOURCES.md):",
        "",
    ]
    for s in sources:
        info = result["real"][s]
        lines.append(f"- **{short[s]}** `{s}`: {info['description']}, {info['frames']} scan(s)")
    for entry in result["skipped"]:
        lines.append(f"- {entry['status']}: `{entry['name']}`: {entry['reason']}")
    lines += [
        "",
        "Each world against the sources of its own sensor (mean ± std over seeds; JS distances base 2, 0 = identical;"
        " `class rem. JS` = per-class remission JS, macro mean over classes, labelled sources only; pts/scan, mixed"
        " (share of depth edges with an in-between return) and rough. (median range roughness < 20 m) are the"
        " world's own values, the real ones in the last row; `-` = other sensor):",
        "",
        "| world (sensor) | " + " | ".join(f"{short[s]} {head}" for s, _, head, _ in columns) + " |",
        "|---|" + "---|" * len(columns),
    ]
    for preset, world in result["worlds"].items():
        cells = [
            _cell(world["summary"][s][key], fmt) if world["summary"][s]["same_sensor"] else "-"
            for s, key, _, fmt in columns
        ]
        lines.append(f"| `{preset}` ({SENSOR_NAMES[world['sensor']]}) | " + " | ".join(cells) + " |")
    real_cells = []
    for s, key, _, fmt in columns:
        info = result["real"][s]
        value = {
            "points_per_scan": info["points_per_scan"],
            "mixed_share": info["edges"]["mixed_share_of_edges"],
            "roughness_mm": info["edges"]["roughness_median_mm"],
        }.get(key)
        real_cells.append("" if value is None else format(value, fmt))
    lines.append("| real source | " + " | ".join(real_cells) + " |")
    lines += [
        "",
        "Every pair, also across sensors (range / elevation / remission JS, mean over seeds; a real source against the "
        "other real sources gives the floor of the same sensor and the cost of a sensor change):",
        "",
        "| world | " + " | ".join(f"{short[s]} range / elev. / rem. JS" for s in sources) + " |",
        "|---|" + "---|" * len(sources),
    ]
    for preset, world in result["worlds"].items():
        cells = []
        for s in sources:
            row = world["summary"][s]
            cells.append(" / ".join(f"{row[k]['mean']:.3f}" for k in ("range_js", "elevation_js", "intensity_js")))
        lines.append(f"| `{preset}` ({SENSOR_NAMES[world['sensor']]}) | " + " | ".join(cells) + " |")
    for a in sources:
        cells = []
        for b in sources:
            pair = result["real_vs_real"][a][b]
            cells.append(" / ".join(f"{pair[k]:.3f}" for k in ("range_js", "elevation_js", "intensity_js")))
        lines.append(f"| real {short[a]} | " + " | ".join(cells) + " |")
    labelled = [s for s in sources if result["real"][s]["labelled"]]
    for s in labelled:
        worlds = [p for p, w in result["worlds"].items() if w["summary"][s]["same_sensor"]]
        seeds_of = [r["sources"][s] for p in worlds for r in result["worlds"][p]["seeds"]]
        classes = sorted({c for pair in seeds_of for c in pair["class_intensity_js_per_class"]})
        lines += ["", f"Remission JS per class against {short[s]} (mean over seeds):", ""]
        lines += ["| class | " + " | ".join(f"`{p}`" for p in worlds) + " |", "|---|" + "---|" * len(worlds)]
        for c in classes:
            cells = []
            for p in worlds:
                values = [r["sources"][s]["class_intensity_js_per_class"].get(c) for r in result["worlds"][p]["seeds"]]
                stat = mean_std(values)
                cells.append("-" if stat is None else f"{stat['mean']:.3f}")
            lines.append(f"| {c} | " + " | ".join(cells) + " |")
    lines += ["", f"Command: `{result['command']}` ({result['seconds'] / 60:.1f} min)", ""]
    return "\n".join(lines)


def plot(path: Path, result: dict) -> Path:
    """PNG of the remission histogram of every return, per source: the real one against each same-sensor world."""
    from u4d_aug.viz import plt, save_figure

    sources = list(result["real"])
    fig, axes = plt.subplots(1, len(sources), figsize=(5 * len(sources), 3.6), squeeze=False)
    centers = (INTENSITY_BINS[:-1] + INTENSITY_BINS[1:]) / 2
    centers[0] = 0.0
    for k, (ax, s) in enumerate(zip(axes[0], sources)):
        real = np.asarray(result["real"][s]["intensity_hist"], dtype=float)
        ax.step(centers, real / real.sum(), where="mid", color="black", lw=2, label="real")
        for preset, world in result["worlds"].items():
            if not world["summary"][s]["same_sensor"]:
                continue
            hist = np.asarray(world["intensity_hist_pooled"], dtype=float)
            js = world["summary"][s]["intensity_js"]["mean"]
            ax.step(centers, hist / hist.sum(), where="mid", label=f"{preset} (JS {js:.3f})")
        ax.set_yscale("log")
        ax.set_xlim(-0.02, 1.0)
        ax.set_xlabel("remission (nuScenes: intensity / 255); first bin < 0.005")
        info = result["real"][s]
        ax.set_title(f"S{k + 1} {s}\n{SENSOR_NAMES[info['sensor']]}, {info['frames']} real scan(s)", fontsize=9)
        ax.legend(fontsize=8)
    fig.suptitle("remission of every return, seeds pooled, sim vs real per source", fontsize=10, y=1.04)
    return save_figure(fig, path)


def run(args: argparse.Namespace) -> int:
    """Measure, print the tables, write <name>.json / .md / _remission.png."""
    if not args.real.is_dir():
        print(
            f"no real scans at {args.real}: expected ../shared/data/real beside the checkout (see its SOURCES.md), "
            "or set U4D_REAL_DATA / --real",
            file=sys.stderr,
        )
        return 1
    sources, skipped = find_sources(args.real)
    if not sources:
        print(f"no usable real scan source under {args.real}", file=sys.stderr)
        return 1
    presets = {name: PRESETS[name] for name in args.presets}
    start = time.perf_counter()
    result = {
        "name": args.name,
        "command": "python benchmarks/bench_sim_realism_sources.py " + " ".join(sys.argv[1:]),
        "real_root": str(args.real),
        "seeds": args.seeds,
        "sequences": args.sequences,
        "frames": args.frames,
        "skipped": skipped,
        **measure(sources, presets, args.seeds, args.sequences, args.frames),
    }
    result["seconds"] = time.perf_counter() - start
    text = markdown(result)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out / f"{args.name}.json", result)
    atomic_write_text(args.out / f"{args.name}.md", text)
    png = plot(args.out / f"{args.name}_remission.png", result)
    print(f"wrote {args.out / args.name}.json, .md and {png}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--sequences", type=int, default=12, help="places per world")
    parser.add_argument("--frames", type=int, default=3, help="consecutive scans per place")
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS))
    parser.add_argument("--name", default="sim_realism_sources", help="result file stem")
    parser.add_argument("--out", type=Path, default=RESULTS, help="result folder")
    parser.add_argument("--real", type=Path, default=REAL, help="real-data folder laid out as its SOURCES.md says")
    args = parser.parse_args(argv)
    if args.sequences < 1 or args.frames < 1:
        parser.error("--sequences and --frames must be >= 1")
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
