"""Fit the measured surface model (u4d_aug/data/sim/surfaces.py MEASURED) to the labelled real SemanticKITTI frames.

Renders `--places` x `--frames` scans of the default (seq-00) street layout with the sensor terms of the fit
(`--set`, by default those configs/sim/varied.yaml had when MEASURED was fitted) but a clean remission pipeline
(no noise, no zero threshold, gain 1, no speckle, no zeros), so each labelled return within 50 m keeps its signal
S = reflectivity x incidence x range falloff, its material and its class. The remission model of the measured
surfaces is then evaluated offline on those returns with fixed random numbers,

    I = S x gain_m x exp(speckle_m z1 - speckle_m^2 / 2) + noise z2,  0 if I < U(0.02, 0.10) or u < zero_m,

and gain (0.6-1.5), speckle (0-0.6) and, for the materials in ZERO_FIT, the zero probability (0-0.3) of every
material are chosen by coordinate descent (3 sweeps over grids) to minimise the mean of the macro and the
share-weighted per-class remission JS distance against ../shared/data/real/semantickitti (frames 0-2). Prints the
table to paste into MEASURED and writes benchmarks/results/world/sim_surface_fit.json.

    python benchmarks/diagnostics/fit_sim_surfaces.py [--places 8] [--frames 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from u4d_aug.config import load_config
from u4d_aug.data.labels import map_semantickitti
from u4d_aug.data.sensors import hdl64
from u4d_aug.data.sim.agents import dynamic_mesh
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import MATERIALS, TriangleMesh
from u4d_aug.data.sim.raycast import LidarSimulator, ray_pattern
from u4d_aug.data.sim.report import INTENSITY_BINS, LABEL_RANGE, dataset_stats, intensity_distances
from u4d_aug.data.sim.writer import build_sequence
from u4d_aug.io import atomic_write_json

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results" / "world"
REAL = Path(os.environ.get("U4D_REAL_DATA") or ROOT.parent / "shared" / "data" / "real") / "semantickitti"
FIT_SET = ["lidar.surface_model=measured", "lidar.range_noise=0.008", "objects.sign_back_metal=true"]
CLEAN = ["lidar.intensity_noise=0", "lidar.zero_threshold=[0, 0]", "lidar.intensity_step=0.0001"]
ZERO_FIT = {"asphalt", "leaves", "hedge", "bark", "grass", "car_paint", "metal", "plastic", "paving", "facade"}
GRIDS = {
    "gain": np.linspace(0.6, 1.5, 19),
    "speckle": np.linspace(0.0, 0.6, 13),
    "zero": np.array([0.0, 0.01, 0.02, 0.04, 0.06, 0.08, 0.1, 0.15, 0.2, 0.25, 0.3]),
}


def _with_material(mesh: TriangleMesh) -> TriangleMesh:
    """The mesh with each triangle's material index in its instance channel (so a scan reports the material)."""
    return TriangleMesh(
        mesh.vertices, mesh.triangles, mesh.semantic, mesh.material.astype(np.uint16), mesh.material, mesh.reflectivity
    )


def signals(cfg: SimConfig, places: int, frames: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train id, material index, signal) of every labelled return within LABEL_RANGE, clean remission pipeline."""
    sensor = hdl64()
    classes, materials, signal = [], [], []
    for index in range(places):
        seq = build_sequence(seed, index, frames, sensor, cfg)
        pattern = ray_pattern(sensor, cfg.lidar, np.random.default_rng([seed, index, 0, 3]))
        sim = LidarSimulator(_with_material(seq.world.mesh), sensor, cfg.lidar, pattern)
        sim._terms.zero_prob[:] = 0.0  # the fit decides every material's zeros, gain and speckle
        sim._terms.gain[:] = 1.0
        sim._terms.speckle[:] = 0.0
        for frame in range(frames):
            hills = seq.world.network.warp.hills
            dynamic = dynamic_mesh(seq.agents, frame, seq.ego.xy[frame], seq.cfg.view_radius, hills)
            if dynamic.num_triangles:
                dynamic = _with_material(dynamic)
            scan = sim.scan(seq.ego.poses[frame], dynamic, np.random.default_rng([seed, index, 1, frame]))
            near = np.linalg.norm(scan.points[:, :3], axis=1) <= LABEL_RANGE
            classes.append(map_semantickitti(scan.semantic[near]))
            materials.append(scan.instance[near].astype(np.int64))
            signal.append(scan.points[near, 3].astype(np.float64))
    return np.concatenate(classes), np.concatenate(materials), np.concatenate(signal)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--places", type=int, default=8)
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=FIT_SET, metavar="KEY=VALUE", help="sensor terms of the fit")
    parser.add_argument("--real", type=Path, default=REAL)
    args = parser.parse_args()
    real = dataset_stats(args.real)["intensity_hist"]
    start = time.perf_counter()
    cfg = load_config(SimConfig, None, [*args.set, *CLEAN])
    train, material, signal = signals(cfg, args.places, args.frames, args.seed)
    print(f"{len(train)} labelled returns in {time.perf_counter() - start:.0f} s", flush=True)
    rng = np.random.default_rng(0)
    z1, z2 = rng.standard_normal(len(train)), rng.standard_normal(len(train))
    threshold, u = rng.uniform(0.02, 0.10, len(train)), rng.random(len(train))
    params = {
        "gain": np.ones(len(MATERIALS)),
        "speckle": np.zeros(len(MATERIALS)),
        "zero": np.array([m.zero_prob for m in MATERIALS]),
    }
    noise = 0.04
    bins = len(INTENSITY_BINS) - 1

    def objective() -> tuple[float, dict]:
        s = params["speckle"][material]
        value = signal * params["gain"][material] * np.exp(s * z1 - s * s / 2) + noise * z2
        value = np.where((value < threshold) | (u < params["zero"][material]), 0.0, value)
        value = np.clip(np.floor(value / 0.01 + 1e-6) * 0.01, 0.0, 0.99)
        index = np.clip(np.searchsorted(INTENSITY_BINS, value, side="right") - 1, 0, bins - 1)
        hist = np.bincount(train * bins + index, minlength=20 * bins).reshape(20, bins)
        js = intensity_distances(hist, real)
        return 0.5 * js["mean"] + 0.5 * js["weighted"], js

    present = [k for k in range(len(MATERIALS)) if (material == k).sum() > 300]
    best, js = objective()
    print(f"start: objective {best:.4f}")
    for sweep in range(3):
        for value in np.linspace(0.0, 0.08, 9):
            old, noise = noise, value
            trial = objective()[0]
            if trial < best:
                best = trial
            else:
                noise = old
        for k in present:
            for name, grid in GRIDS.items():
                if name == "zero" and MATERIALS[k].name not in ZERO_FIT:
                    continue
                for value in grid:
                    old = params[name][k]
                    params[name][k] = value
                    trial = objective()[0]
                    if trial < best - 1e-6:
                        best = trial
                    else:
                        params[name][k] = old
        best, js = objective()
        print(f"sweep {sweep}: objective {best:.4f}, JS mean {js['mean']:.3f}, weighted {js['weighted']:.3f}")
    fitted = {}
    for k in present:
        name = MATERIALS[k].name
        fitted[name] = {key: float(params[key][k]) for key in params}
        parts = [f"gain={params['gain'][k]:.2f}"]
        if params["speckle"][k]:
            parts.append(f"speckle={params['speckle'][k]:.2f}")
        if abs(params["zero"][k] - MATERIALS[k].zero_prob) > 1e-9:
            parts.append(f"zero_prob={params['zero'][k]:.2f}")
        print(f'    "{name}": SurfaceFit({", ".join(parts)}),')
    result = {"set": args.set, "places": args.places, "frames": args.frames, "intensity_noise": noise, **js}
    result["materials"] = fitted
    atomic_write_json(RESULTS / "sim_surface_fit.json", result)
    print(f"wrote {RESULTS / 'sim_surface_fit.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
