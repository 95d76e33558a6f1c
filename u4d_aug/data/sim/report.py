"""`u4d sim-report`: do simulated scans look like real ones (points/scan, rings, range, elevation, classes).

Range histogram: 1 m bins over 0-80 m, compared with the Jensen-Shannon distance (scipy `jensenshannon`,
base 2, so 0 = identical and 1 = disjoint). A reference of a few consecutive real frames shows one place, so the
report also measures how far one place of the simulated world lies from the simulated pool (`place_spread`:
the same JS between the first n consecutive frames of each simulated sequence, n = the real frame count, and
the pooled simulated histogram); a sim-vs-real JS inside that spread is as close as one place can get.
Rings are recovered from the storage order (KITTI stores one ring after the other in azimuth order; a new ring
starts where the azimuth wraps around), as in data/sensors.py.

Surfaces: remission histograms (a bin of its own for 0, then 0.05 steps) of every return (`intensity_all`) and, for
labelled scans, per class over the returns within `LABEL_RANGE`; their JS distance sim vs real, class by class, as a
macro mean over the classes both hold (`MIN_CLASS_POINTS`) and weighted by the real class shares. Edges and noise
(`edge_stats`, neighbours along a ring): the range roughness (median |second difference| of range over smooth triples
within 20 m: range noise), and the share of depth edges with a return floating between the two sides (mixed pixels).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from scipy.spatial.distance import jensenshannon

from u4d_aug.data.formats import load_kitti_frame
from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, SEMANTICKITTI_IGNORE, map_semantickitti
from u4d_aug.errors import InputError
from u4d_aug.io import check_output_file, dumps_json

RANGE_BINS = np.arange(0.0, 81.0, 1.0)  # 1 m bins, 0-80 m
ELEVATION_BINS = np.arange(-26.0, 4.01, 0.5)  # degrees
MAX_RINGS = 128
INTENSITY_BINS = np.concatenate([[0.0, 0.005], np.arange(0.05, 1.001, 0.05)])  # exact 0, then 0.05 steps
LABEL_RANGE = 50.0  # m: the real seq-00 labels stop here
MIN_CLASS_POINTS = 200  # a class enters the intensity JS means when sim and real both hold this many returns
EDGE_JUMP, MIXED_GAP, SMOOTH_JUMP, SMOOTH_RANGE = 1.0, 0.3, 0.3, 20.0  # m, see edge_stats
SIDE_FLAT = 0.03  # relative range change between neighbours on one side of a depth step
ROUGHNESS_BINS = np.concatenate([np.arange(0.0, 0.1, 0.002), [0.1, np.inf]])  # m, |second difference| of range


def rings_from_storage(points: np.ndarray, debounce: int = 500) -> np.ndarray:
    """(N,) ring index of each point of a ring-major scan: a ring ends where the azimuth wraps around."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    azimuth = np.mod(np.arctan2(xyz[:, 1], xyz[:, 0]) - np.arctan2(xyz[0, 1], xyz[0, 0]), 2.0 * np.pi)
    starts = [0]
    for index in np.flatnonzero(np.diff(azimuth) < -np.pi) + 1:
        if index - starts[-1] >= debounce:
            starts.append(int(index))
    ring = np.zeros(len(xyz), dtype=np.int64)
    ring[starts[1:]] = 1
    return np.cumsum(ring)


def edge_stats(points: np.ndarray, ring: np.ndarray) -> dict:
    """Counts over runs of neighbours along a ring (storage order, each < 1 deg from the next).

    Five in a row r0..r4: a depth step has flat sides (|r1 - r0| and |r4 - r3| < SIDE_FLAT of their range) and
    |r3 - r1| > EDGE_JUMP; it counts once in `edges` (the window whose middle return r2 is in between, or else on
    the side of r1), and in `mixed` when r2 lies > MIXED_GAP m from both sides (a return from both surfaces at
    once). Three in a row within SMOOTH_RANGE m whose outer two lie within SMOOTH_JUMP m give the range roughness
    |r0 - 2 r1 + r2| (`roughness_hist` over ROUGHNESS_BINS).
    """
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    r = np.linalg.norm(xyz, axis=1)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    near = (ring[1:] == ring[:-1]) & (np.abs(np.angle(np.exp(1j * np.diff(azimuth)))) < np.radians(1.0))
    ok3 = near[:-1] & near[1:]
    r0, r1, r2 = r[:-2][ok3], r[1:-1][ok3], r[2:][ok3]
    smooth = (np.abs(r2 - r0) < SMOOTH_JUMP) & (np.maximum(np.maximum(r0, r1), r2) < SMOOTH_RANGE)
    smooth &= np.abs(r1 - r0) < SMOOTH_JUMP
    second = np.abs(r0 - 2.0 * r1 + r2)[smooth]
    ok5 = near[:-3] & near[1:-2] & near[2:-1] & near[3:]
    a, b, c, d, e = (r[k : len(r) - 4 + k][ok5] for k in range(5))
    flat = (np.abs(b - a) < SIDE_FLAT * b) & (np.abs(e - d) < SIDE_FLAT * d)
    between = (c - np.minimum(b, d) > MIXED_GAP) & (np.maximum(b, d) - c > MIXED_GAP)
    # one window per step: the middle return in between, or the last one before the step (not the first after it)
    edges = flat & (np.abs(d - b) > EDGE_JUMP) & (between | (np.abs(c - b) < SIDE_FLAT * b))
    return {
        "edges": int(edges.sum()),
        "mixed": int((edges & between).sum()),
        "smooth": int(smooth.sum()),
        "roughness_hist": np.histogram(second, ROUGHNESS_BINS)[0],
    }


def _intensity_bin(intensity: np.ndarray) -> np.ndarray:
    """(N,) INTENSITY_BINS index of each remission; values outside [0, 1] fall into the end bins."""
    return np.clip(np.searchsorted(INTENSITY_BINS, intensity, side="right") - 1, 0, len(INTENSITY_BINS) - 2)


def intensity_hist(points: np.ndarray, semantic: np.ndarray) -> np.ndarray:
    """(SEMANTICKITTI_IGNORE + 1, bins) remission histogram per train id of the returns within LABEL_RANGE."""
    train = map_semantickitti(semantic)
    near = np.linalg.norm(points[:, :3].astype(np.float64), axis=1) <= LABEL_RANGE
    bins = _intensity_bin(points[:, 3])
    num = len(INTENSITY_BINS) - 1
    flat = np.bincount(train[near] * num + bins[near], minlength=(SEMANTICKITTI_IGNORE + 1) * num)
    return flat.reshape(SEMANTICKITTI_IGNORE + 1, num)


def intensity_distances(sim_hist: np.ndarray, real_hist: np.ndarray) -> dict:
    """Per-class remission JS distance (base 2) sim vs real, its macro mean and its mean weighted by real shares,
    over the classes both hold MIN_CLASS_POINTS returns of."""
    per_class = {}
    weights = {}
    for k, name in enumerate(SEMANTICKITTI_CLASSES):
        if sim_hist[k].sum() >= MIN_CLASS_POINTS and real_hist[k].sum() >= MIN_CLASS_POINTS:
            per_class[name] = float(jensenshannon(sim_hist[k], real_hist[k], base=2))
            weights[name] = float(real_hist[k].sum())
    total = sum(weights.values())
    return {
        "per_class": per_class,
        "mean": float(np.mean(list(per_class.values()))) if per_class else None,
        "weighted": sum(per_class[n] * weights[n] for n in per_class) / total if total else None,
        "zero_share": {
            name: {
                "sim": float(sim_hist[k, 0] / max(sim_hist[k].sum(), 1)),
                "real": float(real_hist[k, 0] / max(real_hist[k].sum(), 1)),
            }
            for k, name in enumerate(SEMANTICKITTI_CLASSES)
            if name in per_class
        },
    }


def edge_summary(stats: dict) -> dict:
    """Mixed-pixel share of depth edges and the median range roughness (mm) of a dataset's summed edge counts."""
    hist = stats["roughness_hist"]
    cdf = np.cumsum(hist) / max(hist.sum(), 1)
    k = int(np.searchsorted(cdf, 0.5))
    median = 1000.0 * (ROUGHNESS_BINS[k] + ROUGHNESS_BINS[min(k + 1, len(ROUGHNESS_BINS) - 2)]) / 2
    return {
        "mixed_share_of_edges": stats["mixed"] / max(stats["edges"], 1),
        "edges_per_scan": stats["edges"] / stats["frames"],
        "roughness_median_mm": float(median),
    }


def scan_stats(
    points: np.ndarray,
    semantic: np.ndarray | None = None,
    ring: np.ndarray | None = None,
    elevation_bins: np.ndarray = ELEVATION_BINS,
) -> dict:
    """Histograms of one scan: range, elevation, points per ring, remission of every return, train-id class counts
    and per-class remission (if labelled); ring None = recovered from the storage order (ring-major scans)."""
    xyz = points[:, :3].astype(np.float64)
    r = np.linalg.norm(xyz, axis=1)
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    ring = rings_from_storage(points) if ring is None else np.asarray(ring, dtype=np.int64)
    stats = {
        "points": len(points),
        "range_hist": np.histogram(r, RANGE_BINS)[0],
        "elevation_hist": np.histogram(elevation, elevation_bins)[0],
        "intensity_all": np.bincount(_intensity_bin(points[:, 3]), minlength=len(INTENSITY_BINS) - 1),
        "ring_counts": np.bincount(np.minimum(ring, MAX_RINGS - 1), minlength=MAX_RINGS),
        "num_rings": int(ring.max()) + 1,
        "beyond_50m": float(np.mean(r > 50.0)),
        "median_range": float(np.median(r)),
        "intensity_mean": float(points[:, 3].mean()),
        "intensity_zero": float(np.mean(points[:, 3] == 0)),
    }
    edges = edge_stats(points, ring)
    stats.update(edges)
    if semantic is not None:
        stats["class_counts"] = np.bincount(map_semantickitti(semantic), minlength=SEMANTICKITTI_IGNORE + 1)
        stats["intensity_hist"] = intensity_hist(points, semantic)
    return stats


def _frames(root: Path, max_frames: int) -> list[tuple[Path, Path | None]]:
    scans = sorted((Path(root) / "sequences").glob("*/velodyne/*.bin"))
    if not scans:
        raise InputError(f"{root}: no sequences/*/velodyne/*.bin scans (expected a SemanticKITTI-layout root)")
    if len(scans) > max_frames:
        scans = [scans[i] for i in np.linspace(0, len(scans) - 1, max_frames).round().astype(int)]
    out = []
    for scan in scans:
        label = scan.parent.parent / "labels" / (scan.stem + ".label")
        out.append((scan, label if label.is_file() else None))
    return out


def frames_stats(frames: Iterable[tuple], elevation_bins: np.ndarray = ELEVATION_BINS) -> dict:
    """Summed `scan_stats` histograms of (points, semantic or None, ring or None) scans (class counts and per-class
    remission over the labelled ones)."""
    total: dict = {}
    points, example = [], None
    for scan, semantic, ring in frames:
        stats = scan_stats(scan, semantic, ring, elevation_bins)
        points.append(stats["points"])
        for key in (
            "range_hist",
            "elevation_hist",
            "intensity_all",
            "ring_counts",
            "class_counts",
            "intensity_hist",
            "edges",
            "mixed",
            "smooth",
            "roughness_hist",
        ):
            if key in stats:
                total[key] = total.get(key, 0) + stats[key]
        if example is None:
            example = (scan, semantic)
    if not points:
        raise InputError("frames_stats: no scans")
    total["frames"] = len(points)
    total["points_per_scan"] = float(np.mean(points))
    total["ring_counts"] = total["ring_counts"] / len(points)
    total["example"] = example
    return total


def dataset_stats(root: Path, max_frames: int = 30, elevation_bins: np.ndarray = ELEVATION_BINS) -> dict:
    """Summed histograms over up to `max_frames` scans of a root (class counts over the labelled ones)."""
    frames = (load_kitti_frame(scan, label) for scan, label in _frames(root, max_frames))
    return frames_stats(((frame.points, frame.semantic, None) for frame in frames), elevation_bins)


def _range_hist(scan_path: Path) -> np.ndarray:
    points = load_kitti_frame(scan_path).points
    return np.histogram(np.linalg.norm(points[:, :3].astype(np.float64), axis=1), RANGE_BINS)[0]


def place_spread(root: Path, frames_per_place: int, pooled: np.ndarray, max_places: int = 16) -> dict:
    """Range JS between each sequence's first `frames_per_place` consecutive scans and the pooled histogram.

    Returns {"frames_per_place", "places", "median", "min", "max", "per_place"} over up to `max_places` sequences
    holding at least that many scans.
    """
    per_place = {}
    for sequence in sorted((Path(root) / "sequences").glob("*/velodyne")):
        scans = sorted(sequence.glob("*.bin"))
        if len(scans) < frames_per_place or len(per_place) >= max_places:
            continue
        hist = sum(_range_hist(scan) for scan in scans[:frames_per_place])
        per_place[sequence.parent.name] = float(jensenshannon(hist, pooled, base=2))
    values = list(per_place.values())
    return {
        "frames_per_place": frames_per_place,
        "places": len(values),
        "median": float(np.median(values)) if values else None,
        "min": min(values) if values else None,
        "max": max(values) if values else None,
        "per_place": per_place,
    }


def compare(sim_root: Path, real_root: Path, max_frames: int = 30) -> tuple[dict, dict, dict]:
    """(report dict, sim stats, real stats)."""
    sim, real = dataset_stats(sim_root, max_frames), dataset_stats(real_root, max_frames)
    report = {
        "sim_root": str(sim_root),
        "real_root": str(real_root),
        "frames": {"sim": sim["frames"], "real": real["frames"]},
        "points_per_scan": {"sim": sim["points_per_scan"], "real": real["points_per_scan"]},
        "range_js": float(jensenshannon(sim["range_hist"], real["range_hist"], base=2)),
        "elevation_js": float(jensenshannon(sim["elevation_hist"], real["elevation_hist"], base=2)),
        "range_js_place_spread": place_spread(sim_root, real["frames"], sim["range_hist"]),
        "range_share": {},
        "points_per_ring": {
            "sim": np.round(sim["ring_counts"][: _rings(sim)], 1).tolist(),
            "real": np.round(real["ring_counts"][: _rings(real)], 1).tolist(),
        },
        "class_share": {},
        "edges": {"sim": edge_summary(sim), "real": edge_summary(real)},
    }
    if "intensity_hist" in sim and "intensity_hist" in real:
        report["intensity_js"] = intensity_distances(sim["intensity_hist"], real["intensity_hist"])
    for name, (lo, hi) in {"<5m": (0, 5), "5-20m": (5, 20), "20-50m": (20, 50), ">50m": (50, 80)}.items():
        report["range_share"][name] = {
            key: float(stats["range_hist"][lo:hi].sum() / stats["range_hist"].sum())
            for key, stats in (("sim", sim), ("real", real))
        }
    names = (*SEMANTICKITTI_CLASSES, "ignore")
    for key, stats in (("sim", sim), ("real", real)):
        counts = stats.get("class_counts")
        if counts is not None:
            share = counts / max(counts.sum(), 1)
            for i, name in enumerate(names):
                report["class_share"].setdefault(name, {})[key] = float(share[i])
    return report, sim, real


def _rings(stats: dict) -> int:
    nonzero = np.flatnonzero(stats["ring_counts"] > 0)
    return int(nonzero[-1]) + 1 if len(nonzero) else 0


def plot_report(path: Path, report: dict, sim: dict, real: dict) -> Path:
    """Side-by-side PNG: range/elevation/ring/class histograms, then BEV and range image of one scan each."""
    from u4d_aug.viz import add_colorbar, class_legend, draw_bev, draw_semantic_bev, plt, save_figure

    fig = plt.figure(figsize=(16, 18))
    grid = fig.add_gridspec(4, 2, height_ratios=[1, 1, 2.2, 0.7], hspace=0.45, wspace=0.3)  # room for labels
    ax = fig.add_subplot(grid[0, 0])
    for key, stats in (("sim", sim), ("real", real)):
        ax.step(RANGE_BINS[:-1], stats["range_hist"] / stats["range_hist"].sum(), where="post", label=key)
    ax.set_title(f"range histogram (1 m bins), JS distance {report['range_js']:.3f}", fontsize=10)
    ax.set_xlabel("range [m]")
    ax.legend()
    ax = fig.add_subplot(grid[0, 1])
    for key, stats in (("sim", sim), ("real", real)):
        ax.step(
            ELEVATION_BINS[:-1],
            stats["elevation_hist"] / stats["elevation_hist"].sum(),
            where="post",
            label=key,
        )
    ax.set_title(f"elevation histogram (0.5 deg), JS {report['elevation_js']:.3f}", fontsize=10)
    ax.set_xlabel("elevation [deg]")
    ax.legend()
    ax = fig.add_subplot(grid[1, 0])
    for key in ("sim", "real"):
        ax.plot(report["points_per_ring"][key], marker=".", label=key)
    ax.set_title(
        f"points per ring (storage order); points/scan sim {report['points_per_scan']['sim']:.0f}, "
        f"real {report['points_per_scan']['real']:.0f}",
        fontsize=10,
    )
    ax.legend()
    ax = fig.add_subplot(grid[1, 1])
    names = list(report["class_share"])
    x = np.arange(len(names))
    for k, key in enumerate(("sim", "real")):
        ax.bar(x + (k - 0.5) * 0.4, [report["class_share"][n].get(key, 0.0) for n in names], 0.4, label=key)
    ax.set_xticks(x, names, rotation=70, fontsize=8)
    ax.set_yscale("log")
    ax.set_title("class share (train ids)", fontsize=10)
    ax.legend()
    examples = {"sim": sim["example"], "real": real["example"]}
    for k, (key, (points, semantic)) in enumerate(examples.items()):
        bev = fig.add_subplot(grid[2, k])
        if semantic is not None:
            draw_semantic_bev(bev, points, map_semantickitti(semantic), title=f"{key}: BEV", legend=False,
                              extent=40.0, point_size=0.3)  # fmt: skip
        else:
            draw_bev(bev, points, extent=40.0, title=f"{key}: BEV, coloured by height", point_size=0.3)
        ax = fig.add_subplot(grid[3, k])
        image = ax.imshow(_range_image(points), cmap="turbo", aspect="auto", interpolation="nearest", vmin=0, vmax=40)
        ax.set_title(f"{key}: range image (rings x 1024 azimuth bins; white: no return)", fontsize=9)
        ax.set_xticks([])
        ax.set_ylabel("ring", fontsize=8)
        add_colorbar(ax, image, "range [m]")
    labelled = [map_semantickitti(semantic) for _, semantic in examples.values() if semantic is not None]
    if labelled:  # one legend of both scans' classes, right of the last BEV (a left one would cover the right BEV)
        class_legend(bev, np.concatenate(labelled))
    return save_figure(fig, path)


def plot_intensity(path: Path, report: dict, sim: dict, real: dict) -> Path:
    """PNG of the per-class remission histograms, sim against real, with each class's JS distance."""
    from u4d_aug.viz import plt, save_figure

    names = list(report["intensity_js"]["per_class"])
    cols = 4
    rows = max(1, int(np.ceil(len(names) / cols)))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False)
    centers = (INTENSITY_BINS[:-1] + INTENSITY_BINS[1:]) / 2
    centers[0] = 0.0
    for ax, name in zip(axes.ravel(), names):
        k = SEMANTICKITTI_CLASSES.index(name)
        for key, stats in (("sim", sim), ("real", real)):
            hist = stats["intensity_hist"][k]
            ax.step(centers, hist / hist.sum(), where="mid", label=key)
        ax.set_title(f"{name}: JS {report['intensity_js']['per_class'][name]:.3f}", fontsize=9)
        ax.set_xlim(-0.02, 1.0)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(names) :]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=8)
    js = report["intensity_js"]
    fig.suptitle(
        f"remission per class within {LABEL_RANGE:.0f} m (first bin: exactly 0); JS mean {js['mean']:.3f}, "
        f"weighted by real shares {js['weighted']:.3f}",
        fontsize=10,
    )
    return save_figure(fig, path)


def _range_image(points: np.ndarray, width: int = 1024) -> np.ndarray:
    ring = rings_from_storage(points)
    azimuth = np.mod(np.arctan2(points[:, 1], points[:, 0]), 2 * np.pi)
    col = np.minimum((azimuth / (2 * np.pi) * width).astype(int), width - 1)
    image = np.full((ring.max() + 1, width), np.nan)
    image[ring, col] = np.linalg.norm(points[:, :3], axis=1)
    return image


def add_sim_report_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d sim-report`."""
    parser.add_argument("sim_root", type=Path, help="simulated SemanticKITTI-layout root")
    parser.add_argument("--real", type=Path, required=True, help="real SemanticKITTI-layout root")
    parser.add_argument("--png", type=Path, default=None, help="write the side-by-side figure here")
    parser.add_argument(
        "--intensity-png", type=Path, default=None, help="write the per-class remission histograms here"
    )
    parser.add_argument("--json", action="store_true", help="print the report as json")
    parser.add_argument("--max-frames", type=int, default=30, help="scans read per root (evenly spaced)")


def run_sim_report(args: argparse.Namespace) -> int:
    """`u4d sim-report SIM_ROOT --real REAL_ROOT [--png OUT] [--json]`."""
    if args.max_frames < 1:
        raise InputError(f"--max-frames must be >= 1, got {args.max_frames}")
    intensity_png = getattr(args, "intensity_png", None)
    check_output_file(args.png, "figure")
    check_output_file(intensity_png, "figure")
    report, sim, real = compare(args.sim_root, args.real, args.max_frames)
    if args.png is not None:
        report["png"] = str(plot_report(args.png, report, sim, real))
    if intensity_png is not None:
        if "intensity_js" not in report or not report["intensity_js"]["per_class"]:
            raise InputError("--intensity-png: the per-class remission needs labelled scans in both roots")
        report["intensity_png"] = str(plot_intensity(intensity_png, report, sim, real))
    if args.json:
        print(dumps_json(report, indent=2))  # NaN as null
        return 0
    print(f"frames            sim {report['frames']['sim']:>8d}   real {report['frames']['real']:>8d}")
    pps = report["points_per_scan"]
    print(f"points/scan       sim {pps['sim']:>8.0f}   real {pps['real']:>8.0f}")
    print(f"range JS distance {report['range_js']:.3f}   elevation JS distance {report['elevation_js']:.3f}")
    spread = report["range_js_place_spread"]
    if spread["places"]:
        print(
            f"  one simulated place ({spread['frames_per_place']} consecutive scans) vs the simulated pool: "
            f"range JS median {spread['median']:.3f} (min {spread['min']:.3f}, max {spread['max']:.3f}, "
            f"{spread['places']} places)"
        )
    for name, share in report["range_share"].items():
        print(f"  range {name:<7s}  sim {share['sim']:7.2%}   real {share['real']:7.2%}")
    print("class share        sim      real")
    for name, share in report["class_share"].items():
        print(f"  {name:<14s} {share.get('sim', 0.0):7.2%}  {share.get('real', 0.0):7.2%}")
    edges = report["edges"]
    print(
        f"range roughness   sim {edges['sim']['roughness_median_mm']:5.1f} mm   real "
        f"{edges['real']['roughness_median_mm']:5.1f} mm   (median |second difference| along a ring, < 20 m)"
    )
    print(
        f"mixed pixels      sim {edges['sim']['mixed_share_of_edges']:6.2%}   real "
        f"{edges['real']['mixed_share_of_edges']:6.2%}   (share of depth edges with a return between the sides)"
    )
    js = report.get("intensity_js")
    if js and js["per_class"]:
        print(
            f"remission JS per class (within {LABEL_RANGE:.0f} m): mean {js['mean']:.3f}, weighted {js['weighted']:.3f}"
        )
        for name, value in js["per_class"].items():
            zero = js["zero_share"][name]
            print(f"  {name:<14s} JS {value:.3f}   zeros sim {zero['sim']:6.1%}  real {zero['real']:6.1%}")
    for key in ("png", "intensity_png"):
        if key in report:
            print(f"figure: {report[key]}")
    return 0
