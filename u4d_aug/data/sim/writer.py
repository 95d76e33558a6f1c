"""`u4d simulate`: write simulated sequences in the SemanticKITTI layout, deterministic from one seed.

sequences/XX/{velodyne,labels}/NNNNNN.{bin,label}, poses.txt (cam0 frame, SemanticKITTI convention,
relative to frame 0), calib.txt (KITTI odometry seq-00 calibration), times.txt (0.1 s) and manifest.json
(seed + resolved config). Sequence k draws its streets and ego route from np.random.default_rng([seed, k, 0, 0]),
the static world from [seed, k, 0, 1], the agents from [seed, k, 0, 2] and the ray pattern from [seed, k, 0, 3]
(so a change to, say, vegetation settings keeps the street layout), the ground hills from [seed, k, 0, 4] and
frame f from [seed, k, 1, f]; files do not depend on --workers, and a re-run skips frames whose files exist
(writes are atomic).
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from u4d_aug.config import config_to_dict, load_config
from u4d_aug.data.formats import write_calib, write_kitti_label, write_kitti_scan, write_poses, write_times
from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.data.sim.agents import Agent, EgoMotion, dynamic_mesh, ego_motion, make_agents
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.raycast import LidarSimulator, Scan, ray_pattern
from u4d_aug.data.sim.streets import make_hills, make_network
from u4d_aug.data.sim.world import World, build_world
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json, remove_temp_files
from u4d_aug.runlock import run_lock

logger = logging.getLogger(__name__)

MANIFEST_FORMAT = "u4d-sim/1"

# KITTI odometry seq-00 calib.txt (cvlibs.net; also ../shared/data/real/semantickitti/sequences/00/calib.txt):
# camera projections P0..P3 and Tr = velodyne -> cam0, so poses.txt follows the SemanticKITTI convention.
KITTI_CALIB = {
    "P0": [718.856, 0.0, 607.1928, 0.0, 0.0, 718.856, 185.2157, 0.0, 0.0, 0.0, 1.0, 0.0],
    "P1": [718.856, 0.0, 607.1928, -386.1448, 0.0, 718.856, 185.2157, 0.0, 0.0, 0.0, 1.0, 0.0],
    "P2": [718.856, 0.0, 607.1928, 45.38225, 0.0, 718.856, 185.2157, -0.1130887, 0.0, 0.0, 1.0, 0.003779761],
    "P3": [718.856, 0.0, 607.1928, -337.2877, 0.0, 718.856, 185.2157, 2.369057, 0.0, 0.0, 1.0, 0.004915215],
    "Tr": [
        4.276802385584e-04,
        -9.999672484946e-01,
        -8.084491683471e-03,
        -1.198459927713e-02,
        -7.210626507497e-03,
        8.081198471645e-03,
        -9.999413164504e-01,
        -5.403984729748e-02,
        9.999738645903e-01,
        4.859485810390e-04,
        -7.206933692422e-03,
        -2.921968648686e-01,
    ],
}


def kitti_calib() -> dict[str, np.ndarray]:
    """KITTI seq-00 calibration as {key: (3, 4)}."""
    return {k: np.asarray(v, dtype=np.float64).reshape(3, 4) for k, v in KITTI_CALIB.items()}


@dataclass
class SequenceSim:
    """Everything needed to render the frames of one sequence."""

    seed: int
    index: int
    frames: int
    world: World
    ego: EgoMotion
    agents: list[Agent]
    lidar: LidarSimulator
    cfg: SimConfig


def build_sequence(seed: int, index: int, frames: int, sensor: Sensor, cfg: SimConfig, nthreads: int = 0):
    """World, ego motion, agents and the static ray-casting scene of sequence `index` (deterministic)."""
    streets, statics, movers, sensing = (np.random.default_rng([seed, index, 0, k]) for k in range(4))
    extent = frames * cfg.agents.ego_speed[1] / cfg.frame_rate + cfg.view_radius + 250.0
    net = make_network(streets, cfg.street, extent)
    net.warp.hills = make_hills(np.random.default_rng([seed, index, 0, 4]), cfg.street)
    ego = ego_motion(streets, net, cfg, frames)
    world = build_world(statics, cfg, net, ego.route_xy)
    agents = make_agents(movers, world, ego, cfg)
    pattern = ray_pattern(sensor, cfg.lidar, sensing)
    lidar = LidarSimulator(world.mesh, sensor, cfg.lidar, pattern, nthreads=nthreads)
    return SequenceSim(seed, index, frames, world, ego, agents, lidar, cfg)


def render_frame(seq: SequenceSim, frame: int) -> Scan:
    """Ray-cast frame `frame` of a built sequence."""
    dynamic = dynamic_mesh(seq.agents, frame, seq.ego.xy[frame], seq.cfg.view_radius, seq.world.network.warp.hills)
    rng = np.random.default_rng([seq.seed, seq.index, 1, frame])
    return seq.lidar.scan(seq.ego.poses[frame], dynamic, rng)


def sequence_dir(out_dir: Path, index: int) -> Path:
    return Path(out_dir) / "sequences" / f"{index:02d}"


def _frame_done(seq_dir: Path, frame: int) -> bool:
    name = f"{frame:06d}"
    return (seq_dir / "velodyne" / f"{name}.bin").is_file() and (seq_dir / "labels" / f"{name}.label").is_file()


def _simulate_sequence(task: tuple) -> tuple[int, int, int, float]:
    """Worker: write every missing frame of one sequence; returns (index, written, skipped, seconds)."""
    out_dir, index, frames, seed, sensor, cfg, nthreads, progress = task
    start = time.perf_counter()
    seq_dir = sequence_dir(out_dir, index)
    todo = [f for f in range(frames) if not _frame_done(seq_dir, f)]
    if not todo and (seq_dir / "poses.txt").is_file():
        return index, 0, frames, 0.0
    seq = build_sequence(seed, index, frames, get_sensor(sensor), cfg, nthreads)
    calib = kitti_calib()
    write_calib(seq_dir / "calib.txt", calib)
    relative = np.linalg.inv(seq.ego.poses[0]) @ seq.ego.poses  # KITTI poses start at identity
    write_poses(seq_dir / "poses.txt", relative, calib)
    write_times(seq_dir / "times.txt", np.arange(frames) / cfg.frame_rate)
    for frame in todo:
        scan = render_frame(seq, frame)
        write_kitti_scan(seq_dir / "velodyne" / f"{frame:06d}.bin", scan.points)
        write_kitti_label(seq_dir / "labels" / f"{frame:06d}.label", scan.semantic, scan.instance)
        if progress is not None:
            progress.update(1)
    return index, len(todo), frames - len(todo), time.perf_counter() - start


def _manifest(seed: int, sequences: int, frames: int, sensor: str, cfg: SimConfig) -> dict:
    return {
        "format": MANIFEST_FORMAT,
        "seed": seed,
        "sequences": sequences,
        "frames": frames,
        "sensor": sensor,
        "config": config_to_dict(cfg),
    }


def _check_manifest(path: Path, new: dict) -> None:
    """A re-run must use the same seed, frames, sensor and config (more sequences are fine)."""
    import json

    try:
        old = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable manifest ({exc}); use a new --out folder") from None
    for key in ("format", "seed", "frames", "sensor", "config"):
        if old.get(key) != new[key]:
            raise InputError(
                f"{path}: '{key}' differs from this run ({old.get(key)!r} vs {new[key]!r}); "
                "resume with the same settings or use a new --out folder"
            )


def simulate(
    out_dir: str | Path,
    sequences: int,
    frames: int,
    seed: int,
    sensor: str = "hdl64",
    workers: int = 1,
    config: SimConfig | None = None,
    progress: bool = True,
) -> dict:
    """Write `sequences` x `frames` simulated scans under out_dir (resumes); returns a summary dict."""
    if sequences < 1 or frames < 1:
        raise InputError(f"simulate: --sequences and --frames must be >= 1, got {sequences}, {frames}")
    if workers < 1:
        raise InputError(f"simulate: --workers must be >= 1, got {workers}")
    cfg = config if config is not None else SimConfig()
    get_sensor(sensor)  # validate early
    out_dir = Path(out_dir)
    with run_lock(out_dir):  # one run per folder: two would write the same frames
        removed = remove_temp_files(out_dir)
        if removed:
            logger.info("%s: removed %d temp file(s) of a killed run", out_dir, removed)
        manifest_path = out_dir / "manifest.json"
        manifest = _manifest(seed, sequences, frames, str(sensor), cfg)
        if manifest_path.is_file():
            _check_manifest(manifest_path, manifest)
        atomic_write_json(manifest_path, manifest)
        nthreads = max(1, (os.cpu_count() or 1) // workers)
        start = time.perf_counter()
        results = []
        from u4d_aug.progress import progress_bar

        with progress_bar(total=sequences * frames, desc="simulate", unit="frame", enabled=progress) as bar:
            if workers == 1:
                for k in range(sequences):
                    results.append(_simulate_sequence((out_dir, k, frames, seed, str(sensor), cfg, 0, bar)))
            else:
                tasks = [(out_dir, k, frames, seed, str(sensor), cfg, nthreads, None) for k in range(sequences)]
                with multiprocessing.get_context("spawn").Pool(min(workers, sequences)) as pool:
                    for result in pool.imap_unordered(_simulate_sequence, tasks):
                        bar.update(frames)
                        results.append(result)
    written = sum(r[1] for r in results)
    elapsed = time.perf_counter() - start
    return {
        "out": str(out_dir),
        "written": written,
        "skipped": sum(r[2] for r in results),
        "seconds": elapsed,
        "frames_per_second": written / elapsed if written else 0.0,
    }


def add_simulate_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d simulate`."""
    parser.add_argument("--out", type=Path, required=True, help="output root (SemanticKITTI layout)")
    parser.add_argument("--sequences", type=int, default=1)
    parser.add_argument("--frames", type=int, default=100, help="frames per sequence (10 Hz)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sensor", default="hdl64", help="hdl64 | hdl32 | sensor yaml")
    parser.add_argument("--workers", type=int, default=1, help="processes, one sequence each")
    parser.add_argument("--config", type=Path, default=None, help="SimConfig yaml (a file or a preset, e.g. sim/tiny)")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides, e.g. agents.cars_per_100m=3")
    parser.add_argument(
        "--set",
        dest="set_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, as a bare KEY=VALUE does (repeatable)",
    )


def run_simulate(args: argparse.Namespace) -> int:
    """`u4d simulate --out DIR --sequences N --frames F --seed S [--config YAML] [key=value ...]`."""
    overrides = [*(getattr(args, "set_overrides", None) or []), *(getattr(args, "overrides", None) or [])]
    cfg = load_config(SimConfig, args.config, overrides)
    summary = simulate(args.out, args.sequences, args.frames, args.seed, args.sensor, args.workers, cfg)
    print(
        f"wrote {summary['written']} frames ({summary['skipped']} already there) to {summary['out']} "
        f"in {summary['seconds']:.1f} s ({summary['frames_per_second']:.1f} frames/s)"
    )
    return 0
