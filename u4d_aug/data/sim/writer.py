"""`u4d simulate`: write simulated sequences in the SemanticKITTI or the nuScenes layout, deterministic from one seed.

SemanticKITTI (default): sequences/XX/{velodyne,labels}/NNNNNN.{bin,label}, poses.txt (cam0 frame, SemanticKITTI
convention, relative to frame 0), calib.txt (KITTI odometry seq-00 calibration), times.txt (0.1 s).
nuScenes (`--format nuscenes`, HDL-32E by default): sequence k is scene-000k; keyframes every `keyframe_every`
frames (2 Hz by default) in samples/LIDAR_TOP/*.pcd.bin with their lidarseg/v1.0-trainval/<token>_lidarseg.bin
(raw lidarseg ids, `labels.semantickitti_to_nuscenes_raw`), the frames between in sweeps/LIDAR_TOP/ (unlabelled, as
nuScenes), 5 columns x, y, z, intensity 0-255 (on the HDL-32E's scale: sensors.hdl32, its intensity response), ring
(0 = bottom), points in a nuScenes-like lidar frame (x right, y forward); the ego poses of each scene in
sim_ego_poses/scene-000k.npy and, once every scene is written, the v1.0 tables
(`u4d_aug.data.nuscenes.write_nuscenes_tables`). Both layouts get manifest.json (seed + resolved config).
Sequence k draws its streets and ego route from np.random.default_rng([seed, k, 0, 0]),
the static world from [seed, k, 0, 1], the agents from [seed, k, 0, 2] and the ray pattern from [seed, k, 0, 3]
(so a change to, say, vegetation settings keeps the street layout), the ground hills from [seed, k, 0, 4], its street
type (scenes.py, when several have weight) from [seed, k, 0, 5] and frame f from [seed, k, 1, f]; files do not depend
on --workers, and a re-run skips frames whose files exist (writes are atomic). manifest.json records the sensor's
intensity response, the config source (the CONFIG preset or file, or its alias --config, and the overrides) beside
the resolved config, and each place's street type.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import multiprocessing
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from u4d_aug.config import config_from_dict, config_to_dict, load_config
from u4d_aug.data.formats import (
    write_calib,
    write_kitti_label,
    write_kitti_scan,
    write_nuscenes_lidarseg,
    write_nuscenes_scan,
    write_poses,
    write_times,
)
from u4d_aug.data.labels import semantickitti_to_nuscenes_raw
from u4d_aug.data.nuscenes import (
    NUSCENES_VERSION,
    LidarFrame,
    derive_token,
    lidarseg_filename,
    pose_matrix,
    scan_filename,
    write_nuscenes_tables,
)
from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.data.sim.agents import Agent, EgoMotion, dynamic_mesh, ego_motion, make_agents
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.raycast import LidarSimulator, Scan, ray_pattern
from u4d_aug.data.sim.scenes import place_street_type, street_type_config
from u4d_aug.data.sim.streets import make_hills, make_network
from u4d_aug.data.sim.world import World, build_world
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_save_npy, atomic_write_json, load_npy, remove_temp_files
from u4d_aug.outfolder import check_output_folder
from u4d_aug.presets import resolve_config_path
from u4d_aug.runlock import run_lock

logger = logging.getLogger(__name__)

MANIFEST_FORMAT = "u4d-sim/1"
LAYOUTS = ("semantickitti", "nuscenes")
DEFAULT_SENSOR = {"semantickitti": "hdl64", "nuscenes": "hdl32"}

# nuScenes layout: the lidar frame of nuScenes' LIDAR_TOP has x to the right and y forward, a turn of -90 deg about z
# from the simulated sensor frame (x forward): written points are turned by +90 deg, poses keep the geometry.
_SENSOR_FROM_LIDAR = pose_matrix([0.0, 0.0, 0.0], [np.cos(-np.pi / 4), 0.0, 0.0, np.sin(-np.pi / 4)])
LIDAR_AHEAD = 0.94  # m: LIDAR_TOP sits this far ahead of the ego origin (nuScenes: about 0.94 m ahead of the rear axle)


def lidar_to_ego(sensor_height: float) -> np.ndarray:
    """(4, 4) calibrated_sensor of the simulated LIDAR_TOP: LIDAR_AHEAD ahead of and sensor_height above the ego
    origin, which so lies on the road (nuScenes: the rear axle's footprint), turned as nuScenes' lidar frame."""
    mount = np.eye(4)
    mount[:3, 3] = [LIDAR_AHEAD, 0.0, sensor_height]
    return mount @ _SENSOR_FROM_LIDAR


_START_US = 1_600_000_000_000_000  # microseconds of the first frame of scene 0; scene k starts 10^4 s * k later

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
    cfg: SimConfig  # the place's config: the world's, changed by its street type
    street_type: str = "residential"


def build_sequence(seed: int, index: int, frames: int, sensor: Sensor, cfg: SimConfig, nthreads: int = 0):
    """World, ego motion, agents and the static ray-casting scene of sequence `index` (deterministic)."""
    street_type = place_street_type(seed, index, cfg.street_types)
    cfg = street_type_config(cfg, street_type)
    streets, statics, movers, sensing = (np.random.default_rng([seed, index, 0, k]) for k in range(4))
    extent = frames * cfg.agents.ego_speed[1] / cfg.frame_rate + cfg.view_radius + 250.0
    net = make_network(streets, cfg.street, extent)
    net.warp.hills = make_hills(np.random.default_rng([seed, index, 0, 4]), cfg.street)
    ego = ego_motion(streets, net, cfg, frames)
    world = build_world(statics, cfg, net, ego.route_xy)
    agents = make_agents(movers, world, ego, cfg)
    pattern = ray_pattern(sensor, cfg.lidar, sensing)
    lidar = LidarSimulator(world.mesh, sensor, cfg.lidar, pattern, nthreads=nthreads)
    return SequenceSim(seed, index, frames, world, ego, agents, lidar, cfg, street_type)


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
    out_dir, index, frames, seed, sensor, cfg, nthreads, progress, layout, keyframe_every = task
    if layout == "nuscenes":
        return _simulate_scene(out_dir, index, frames, seed, sensor, cfg, nthreads, progress, keyframe_every)
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


# ------------------------------------------------------------------------------------------------------------
# nuScenes layout


def scene_name(index: int) -> str:
    """nuScenes name of simulated sequence `index`: scene-0000, scene-0001, ..."""
    return f"scene-{index:04d}"


def _ego_poses_path(out_dir: Path, index: int) -> Path:
    return Path(out_dir) / "sim_ego_poses" / f"{scene_name(index)}.npy"


def scene_frames(out_dir: Path, index: int, frames: int, seed: int, cfg: SimConfig, keyframe_every: int):
    """The LiDAR frames (list of LidarFrame) of simulated scene `index` as the tables list them (ego poses from its
    written .npy)."""
    ego_to_world = load_npy(_ego_poses_path(out_dir, index), "ego poses of a simulated scene")  # (F, 4, 4)
    out = []
    for frame in range(frames):
        token = derive_token("u4d-sim", seed, index, frame)
        key = frame % keyframe_every == 0
        timestamp = _START_US + index * 10**10 + round(frame * 1e6 / cfg.frame_rate)
        out.append(
            LidarFrame(
                token=token,
                timestamp=timestamp,
                is_key_frame=key,
                filename=scan_filename(f"u4d-sim-{seed}", timestamp, key),
                ego_to_world=ego_to_world[frame],
                lidar_to_ego=lidar_to_ego(cfg.lidar.sensor_height),
                lidarseg=lidarseg_filename(token, NUSCENES_VERSION) if key else None,
            )
        )
    return out


def _scene_frame_done(out_dir: Path, frame: LidarFrame) -> bool:
    return (out_dir / frame.filename).is_file() and (frame.lidarseg is None or (out_dir / frame.lidarseg).is_file())


def _simulate_scene(
    out_dir: Path,
    index: int,
    frames: int,
    seed: int,
    sensor: str,
    cfg: SimConfig,
    nthreads: int,
    progress,
    keyframe_every: int,
) -> tuple[int, int, int, float]:
    """Worker, nuScenes layout: every missing frame of scene `index`, its ego poses first (the tables read them)."""
    start = time.perf_counter()
    poses_path = _ego_poses_path(out_dir, index)
    if poses_path.is_file():
        planned = scene_frames(out_dir, index, frames, seed, cfg, keyframe_every)
        todo = [f for f, frame in enumerate(planned) if not _scene_frame_done(out_dir, frame)]
        if not todo:
            return index, 0, frames, 0.0
    seq = build_sequence(seed, index, frames, get_sensor(sensor), cfg, nthreads)
    lidar_to_world = seq.ego.poses @ _SENSOR_FROM_LIDAR  # (F, 4, 4): the nuScenes-like lidar frame
    atomic_save_npy(poses_path, lidar_to_world @ np.linalg.inv(lidar_to_ego(cfg.lidar.sensor_height)))  # ego -> world
    planned = scene_frames(out_dir, index, frames, seed, cfg, keyframe_every)
    todo = [f for f, frame in enumerate(planned) if not _scene_frame_done(out_dir, frame)]
    turn = _SENSOR_FROM_LIDAR[:3, :3].T.astype(np.float32)  # sensor -> lidar frame
    num_rings = seq.lidar.sensor.num_rings
    for f in todo:
        scan = render_frame(seq, f)
        points = scan.points.copy()
        points[:, :3] = scan.points[:, :3] @ turn.T
        points[:, 3] = np.round(scan.points[:, 3] * 255.0) / 255.0  # nuScenes intensities are integers 0-255
        ring = (num_rings - 1) - scan.ring.astype(np.int64)  # nuScenes counts rings from the bottom
        write_nuscenes_scan(out_dir / planned[f].filename, points, ring)
        if planned[f].lidarseg is not None:
            write_nuscenes_lidarseg(out_dir / planned[f].lidarseg, semantickitti_to_nuscenes_raw(scan.semantic))
        if progress is not None:
            progress.update(1)
    return index, len(todo), frames - len(todo), time.perf_counter() - start


def _manifest(
    seed: int,
    sequences: int,
    frames: int,
    sensor: str,
    cfg: SimConfig,
    layout: str,
    keyframe_every: int,
    config_source: dict | None = None,
):
    manifest = {
        "format": MANIFEST_FORMAT,
        "seed": seed,
        "sequences": sequences,
        "frames": frames,
        "sensor": sensor,
        "sensor_intensity_response": sensor_response(sensor),
        "layout": layout,
        "config_source": config_source or {"config": None, "overrides": []},
        "config": config_to_dict(cfg),
        "street_types": [place_street_type(seed, k, cfg.street_types) for k in range(sequences)],
    }
    if layout == "nuscenes":
        manifest["keyframe_every"] = keyframe_every
    return manifest


def sensor_response(sensor: str) -> list[float]:
    """[floor, gain, gamma] of the sensor's intensity response (sensors.intensity_response), as in manifest.json."""
    resolved = get_sensor(sensor)
    return [resolved.intensity_floor, resolved.intensity_gain, resolved.intensity_gamma]


RESUME_KEYS = ("format", "seed", "frames", "sensor", "sensor_intensity_response", "layout", "keyframe_every", "config")


def _check_manifest(path: Path, new: dict) -> None:
    """A re-run must use the same seed, frames, sensor (and its intensity response), layout and config (more
    sequences are fine)."""
    import json

    try:
        old = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable manifest ({exc}); use a new --out folder") from None
    old.setdefault("layout", "semantickitti")  # written before the nuScenes layout existed
    old.setdefault("sensor_intensity_response", [0.0, 1.0, 1.0])  # written when every sensor reported the remission
    # written before some keys existed: they hold their defaults, which are the old behaviour; a config that no
    # longer reads differs from this run's and is refused below
    with contextlib.suppress(InputError):
        old["config"] = config_to_dict(config_from_dict(SimConfig, old.get("config"), source=str(path)))
    for key in RESUME_KEYS:
        if old.get(key) != new.get(key):
            raise InputError(
                f"{path}: '{key}' differs from this run ({old.get(key)!r} vs {new.get(key)!r}); "
                "resume with the same settings or use a new --out folder"
            )


def check_counts(sequences: int, frames: int, seed: int, workers: int, layout: str) -> None:
    """One line naming the first of `u4d simulate`'s counts that is out of range, or its unknown layout."""
    if sequences < 1 or frames < 1:
        raise InputError(f"simulate: --sequences and --frames must be >= 1, got {sequences}, {frames}")
    if workers < 1:
        raise InputError(f"simulate: --workers must be >= 1, got {workers}")
    if seed < 0:
        raise InputError(f"simulate: --seed must be >= 0 (numpy seeds are non-negative), got {seed}")
    if layout not in LAYOUTS:
        raise InputError(f"simulate: --format {layout!r}: expected one of {', '.join(LAYOUTS)}")


def simulate(
    out_dir: str | Path,
    sequences: int,
    frames: int,
    seed: int,
    sensor: str | None = None,
    workers: int = 1,
    config: SimConfig | None = None,
    progress: bool = True,
    layout: str = "semantickitti",
    keyframe_every: int | None = None,
    config_source: dict | None = None,
) -> dict:
    """Write `sequences` x `frames` simulated scans under out_dir (resumes); returns a summary dict.

    layout 'semantickitti' or 'nuscenes'; sensor None = hdl64 / hdl32 by layout; keyframe_every (nuScenes) None =
    the keyframes at 2 Hz, as nuScenes samples; config_source {"config": preset or file, "overrides": [...]} is
    recorded in manifest.json (which preset wrote the world).
    """
    check_counts(sequences, frames, seed, workers, layout)
    cfg = config if config is not None else SimConfig()
    if keyframe_every is None:
        keyframe_every = max(1, round(cfg.frame_rate / 2.0))
    if keyframe_every < 1:
        raise InputError(f"simulate: --keyframe-every must be >= 1, got {keyframe_every}")
    sensor = DEFAULT_SENSOR[layout] if sensor is None else str(sensor)
    get_sensor(sensor)  # validate early
    out_dir = Path(out_dir)
    with run_lock(out_dir):  # one run per folder: two would write the same frames
        check_output_folder(out_dir, "a simulated world", lambda record: record.get("format") == MANIFEST_FORMAT)
        removed = remove_temp_files(out_dir)
        if removed:
            logger.info("%s: removed %d temp file(s) of a killed run", out_dir, removed)
        manifest_path = out_dir / "manifest.json"
        manifest = _manifest(seed, sequences, frames, sensor, cfg, layout, keyframe_every, config_source)
        source = manifest["config_source"]
        preset = source["config"] or "the built-in defaults (configs/sim/default.yaml)"
        extra = f", overrides {' '.join(source['overrides'])}" if source["overrides"] else ""
        logger.info("%s: world of %s%s (recorded in manifest.json)", out_dir, preset, extra)
        if manifest_path.is_file():
            _check_manifest(manifest_path, manifest)
        atomic_write_json(manifest_path, manifest)
        nthreads = max(1, (os.cpu_count() or 1) // workers)
        start = time.perf_counter()
        results = []
        from u4d_aug.progress import progress_bar

        with progress_bar(total=sequences * frames, desc="simulate", unit="frame", enabled=progress) as bar:
            tasks = [
                (out_dir, k, frames, seed, sensor, cfg, 0 if workers == 1 else nthreads, None, layout, keyframe_every)
                for k in range(sequences)
            ]
            if workers == 1:
                for task in tasks:
                    results.append(_simulate_sequence((*task[:7], bar, *task[8:])))
            else:
                with multiprocessing.get_context("spawn").Pool(min(workers, sequences)) as pool:
                    for result in pool.imap_unordered(_simulate_sequence, tasks):
                        bar.update(frames)
                        results.append(result)
        if layout == "nuscenes":  # every scene's ego poses are on disk now
            scenes = {
                scene_name(k): scene_frames(out_dir, k, frames, seed, cfg, keyframe_every) for k in range(sequences)
            }
            write_nuscenes_tables(out_dir, scenes, NUSCENES_VERSION, log=f"u4d-sim-{seed}")
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
    parser.add_argument("--out", type=Path, required=True, help="output root")
    parser.add_argument(
        "--format",
        choices=LAYOUTS,
        default="semantickitti",
        help="layout: semantickitti (sequences/XX/velodyne) or nuscenes (v1.0 tables, samples/, sweeps/, lidarseg/)",
    )
    parser.add_argument("--sequences", type=int, default=1, help="sequences (nuScenes: scenes scene-0000, ...)")
    parser.add_argument("--frames", type=int, default=100, help="frames per sequence (10 Hz)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--sensor", default=None, help="hdl64 | hdl32 | sensor yaml (default: hdl64, with --format nuscenes hdl32)"
    )
    parser.add_argument(
        "--keyframe-every",
        type=int,
        default=None,
        help="--format nuscenes: every N-th frame is a labelled keyframe (default: 2 Hz, as nuScenes)",
    )
    parser.add_argument("--workers", type=int, default=1, help="processes, one sequence each")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "preset",
        nargs="?",
        type=Path,
        default=None,
        metavar="config",
        help="SimConfig yaml, a file or a preset, e.g. sim/seg_rich (default: the built-in defaults)",
    )
    parser.add_argument("--config", type=Path, default=None, help="the positional config under another name")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides, e.g. agents.cars_per_100m=3")
    parser.add_argument(
        "--set",
        dest="set_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, as a bare KEY=VALUE does (repeatable)",
    )


def config_argument(preset: Path | None, config: Path | None) -> Path | None:
    """The config of `u4d simulate`: the positional one or its alias --config; InputError if both name other files."""
    if preset is None or config is None:
        return preset if preset is not None else config
    if resolve_config_path(preset).resolve() != resolve_config_path(config).resolve():
        raise InputError(f"simulate: config {preset} and --config {config} name different files; give one of them")
    return preset


def run_simulate(args: argparse.Namespace) -> int:
    """`u4d simulate [CONFIG] --out DIR --sequences N --frames F --seed S [key=value ...]`."""
    overrides = [*(getattr(args, "set_overrides", None) or []), *(getattr(args, "overrides", None) or [])]
    config = config_argument(getattr(args, "preset", None), args.config)
    cfg = load_config(SimConfig, config, overrides)
    summary = simulate(
        args.out,
        args.sequences,
        args.frames,
        args.seed,
        args.sensor,
        args.workers,
        cfg,
        layout=getattr(args, "format", "semantickitti"),
        keyframe_every=getattr(args, "keyframe_every", None),
        config_source={"config": None if config is None else str(config), "overrides": overrides},
        progress=not getattr(args, "no_progress", False),
    )
    print(
        f"wrote {summary['written']} frames ({summary['skipped']} already there) to {summary['out']} "
        f"in {summary['seconds']:.1f} s ({summary['frames_per_second']:.1f} frames/s)"
    )
    return 0
