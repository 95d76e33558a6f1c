"""Fit the HDL-32E intensity response (u4d_aug/data/sensors.py hdl32) to the real nuScenes LIDAR_TOP keyframe.

Renders `--places` x `--frames` scans per seed of the nuScenes-like world (`--config`, configs/sim/nuscenes.yaml) with
the HDL-32E whose response is set to the identity, so every return keeps the simulator's remission (KITTI HDL-64E scale,
[0, 1]), and reads the real keyframe(s) under ../shared/data/real/nuscenes_mmdet3d_demo as the project reads nuScenes
(`read_nuscenes_scan`: intensity / 255, returns within 1 m dropped). `sensors.fit_intensity_response` then matches the
quantiles 0.01..0.99 of both (least squares in log intensity) with clip(floor + gain * r ** gamma, 0, 1). Its default
seeds 7-9 are not those bench_sim_realism_sources.py measures (0, 1); gain and gamma trade off against each other where
few simulated returns lie (r > 0.6), so one seed of 12 places moves them by ~0.3 while the curve below r = 0.4 stays
within ~0.01 (at r = 0.5 it spans 0.17-0.21). Prints the values to paste into hdl32(), the remission JS (base 2,
report.INTENSITY_BINS) before and after on the rendered scans, and writes benchmarks/results/world/<name>.json.

    python benchmarks/diagnostics/fit_sensor_response.py [--seeds 7 8 9] [--places 12] [--frames 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.distance import jensenshannon

from u4d_aug.config import load_config
from u4d_aug.data.formats import read_nuscenes_scan
from u4d_aug.data.sensors import RESPONSE_LEVELS, fit_intensity_response, hdl32, intensity_response
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.report import INTENSITY_BINS
from u4d_aug.data.sim.writer import build_sequence, render_frame
from u4d_aug.io import atomic_write_json

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results" / "world"
REAL = Path(os.environ.get("U4D_REAL_DATA") or ROOT.parent / "shared" / "data" / "real") / "nuscenes_mmdet3d_demo"


def simulated_remission(cfg: SimConfig, seeds: list[int], places: int, frames: int) -> np.ndarray:
    """(N,) remission of every return of the rendered scans, HDL-32E rays, identity response, one thread."""
    sensor = dataclasses.replace(hdl32(), intensity_floor=0.0, intensity_gain=1.0, intensity_gamma=1.0)
    out = []
    for seed in seeds:
        for index in range(places):
            seq = build_sequence(seed, index, frames, sensor, cfg, nthreads=1)
            out += [render_frame(seq, frame).points[:, 3] for frame in range(frames)]
    return np.concatenate(out)


def remission_hist(values: np.ndarray) -> np.ndarray:
    """Counts per INTENSITY_BINS bin (exact 0, then 0.05 steps)."""
    bins = np.clip(np.searchsorted(INTENSITY_BINS, values, side="right") - 1, 0, len(INTENSITY_BINS) - 2)
    return np.bincount(bins, minlength=len(INTENSITY_BINS) - 1)


def main(argv: list[str] | None = None) -> int:
    """Render, read the real keyframe(s), fit, print and write the json."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[7, 8, 9])
    parser.add_argument("--places", type=int, default=12)
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--config", default="sim/nuscenes")
    parser.add_argument("--name", default="sensor_response_fit")
    args = parser.parse_args(argv)
    scans = sorted(REAL.glob("**/LIDAR_TOP/*.pcd.bin"))
    if not scans:
        print(f"no nuScenes LIDAR_TOP scans under {REAL}", file=sys.stderr)
        return 1
    start = time.perf_counter()
    real = np.concatenate([read_nuscenes_scan(scan).points[:, 3] for scan in scans])
    sim = simulated_remission(load_config(SimConfig, args.config, []), args.seeds, args.places, args.frames)
    floor, gain, gamma = fit_intensity_response(sim, real)
    fitted = dataclasses.replace(hdl32(), intensity_floor=floor, intensity_gain=gain, intensity_gamma=gamma)
    mapped = intensity_response(fitted, sim)
    real_hist = remission_hist(real)
    result = {
        "command": " ".join(
            ["python benchmarks/diagnostics/fit_sensor_response.py", *(argv if argv is not None else sys.argv[1:])]
        ),
        "config": args.config,
        "seeds": args.seeds,
        "places": args.places,
        "frames": args.frames,
        "real_scans": [str(scan.relative_to(REAL.parent)) for scan in scans],
        "real_points": len(real),
        "sim_points": len(sim),
        "floor": floor,
        "gain": gain,
        "gamma": gamma,
        "js_identity": float(jensenshannon(remission_hist(sim), real_hist, base=2)),
        "js_fitted": float(jensenshannon(remission_hist(mapped), real_hist, base=2)),
        "quantile_levels": [0.1, 0.5, 0.9, 0.99],
        "quantiles": {
            name: np.quantile(values, [0.1, 0.5, 0.9, 0.99]).round(4).tolist()
            for name, values in (("real", real), ("sim_identity", sim), ("sim_fitted", mapped))
        },
        "matched_levels": [float(RESPONSE_LEVELS[0]), float(RESPONSE_LEVELS[-1]), len(RESPONSE_LEVELS)],
        "seconds": time.perf_counter() - start,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    atomic_write_json(RESULTS / f"{args.name}.json", result)
    print(f"intensity_floor={floor:.3f}, intensity_gain={gain:.3f}, intensity_gamma={gamma:.3f}")
    print(f"remission JS on the fit scans: identity {result['js_identity']:.3f}, fitted {result['js_fitted']:.3f}")
    for name, values in result["quantiles"].items():
        print(f"  q10/q50/q90/q99 {name:>12}: {values}")
    print(f"wrote {RESULTS / f'{args.name}.json'} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
