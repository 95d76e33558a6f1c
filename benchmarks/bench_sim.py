"""Simulated-world speed: static scene build time and frames/s written at HDL-64E (64 rings x 2083 azimuths).

Rows: world generation (numpy mesh), static RaycastingScene build (first cast builds the BVH), one frame
with the two-scene strategy (static scene once + small dynamic scene per frame, nearest hit wins) versus
rebuilding one scene with static + dynamic per frame, render + write per frame (steady state), and
end-to-end `simulate` frames/s with 1 and 2 workers: 2 sequences of 100 frames (10 s of driving each; real
SemanticKITTI sequences hold 271-4541 frames), world generation, scene build and the workers' start-up (each
spawned worker imports open3d, ~2 s) included; one run each. The goal is >= 10 frames/s on 2 cores. The
per-frame and build rows are medians of several repetitions. Writes benchmarks/results/speed/sim.json.

    python benchmarks/bench_sim.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from u4d_aug.data.formats import write_kitti_label, write_kitti_scan
from u4d_aug.data.sensors import hdl64
from u4d_aug.data.sim.agents import dynamic_mesh, ego_motion, make_agents
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import concat_meshes
from u4d_aug.data.sim.raycast import LidarSimulator, make_scene, ray_pattern
from u4d_aug.data.sim.streets import make_network
from u4d_aug.data.sim.world import build_world
from u4d_aug.data.sim.writer import simulate
from u4d_aug.io import atomic_write_json

RESULTS = Path(__file__).resolve().parent / "results" / "speed" / "sim.json"


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer frames and repetitions")
    args = parser.parse_args()
    frames = 10 if args.quick else 40  # per-frame rows
    sequence_frames = 10 if args.quick else 100  # end-to-end rows
    repeats = 2 if args.quick else 5
    cfg, sensor = SimConfig(), hdl64()
    rows = {}

    def world_only():
        rng = np.random.default_rng([0, 0, 0])
        net = make_network(rng, cfg.street, frames * 1.2 + cfg.view_radius + 250)
        ego = ego_motion(rng, net, cfg, frames)
        return rng, ego, build_world(rng, cfg, net, ego.route_xy)

    rows["world_generation_s"] = _median_time(world_only, repeats)
    rng, ego, world = world_only()
    agents = make_agents(rng, world, ego, cfg)
    pattern = ray_pattern(sensor, cfg.lidar, rng)
    rows["static_triangles"] = int(world.mesh.num_triangles)

    def scene_build():
        lidar = LidarSimulator(world.mesh, sensor, cfg.lidar, pattern)
        lidar.scan(ego.poses[0], None, np.random.default_rng(0))  # the first cast builds the BVH
        return lidar

    rows["static_scene_build_and_first_cast_s"] = _median_time(scene_build, repeats)
    lidar = scene_build()
    rows["rays_per_frame"] = int(pattern.keep.sum())
    frame_ids = list(range(min(frames, len(ego.poses))))

    def two_scenes():
        for f in frame_ids:
            lidar.scan(ego.poses[f], dynamic_mesh(agents, f, ego.xy[f], cfg.view_radius), np.random.default_rng(f))

    def one_scene_rebuilt():
        for f in frame_ids:
            merged = concat_meshes([world.mesh, dynamic_mesh(agents, f, ego.xy[f], cfg.view_radius)])
            single = LidarSimulator.__new__(LidarSimulator)
            single.__dict__.update(lidar.__dict__, static=merged, scene=make_scene(merged))
            single.scan(ego.poses[f], None, np.random.default_rng(f))

    rows["frame_two_scenes_s"] = _median_time(two_scenes, max(1, repeats // 2)) / len(frame_ids)
    scratch = Path(tempfile.mkdtemp(prefix="bench_sim_write_"))

    def render_and_write():
        for f in frame_ids:
            scan = lidar.scan(
                ego.poses[f], dynamic_mesh(agents, f, ego.xy[f], cfg.view_radius), np.random.default_rng(f)
            )
            write_kitti_scan(scratch / f"{f:06d}.bin", scan.points)
            write_kitti_label(scratch / f"{f:06d}.label", scan.semantic, scan.instance)

    try:
        rows["frame_render_and_write_s"] = _median_time(render_and_write, max(1, repeats // 2)) / len(frame_ids)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    rows["steady_state_fps_1_process"] = 1.0 / rows["frame_render_and_write_s"]
    rows["frame_one_scene_rebuilt_s"] = _median_time(one_scene_rebuilt, 1) / len(frame_ids)
    for workers in (1, 2):
        out = Path(tempfile.mkdtemp(prefix="bench_sim_"))
        try:
            summary = simulate(
                out, sequences=2, frames=sequence_frames, seed=0, workers=workers, config=cfg, progress=False
            )
        finally:
            shutil.rmtree(out, ignore_errors=True)
        rows[f"simulate_fps_workers{workers}"] = summary["frames_per_second"]
        rows[f"simulate_seconds_workers{workers}"] = summary["seconds"]
    rows["frames_per_sequence"] = sequence_frames
    rows["cpu_count"] = os.cpu_count()
    rows["load_average_1min"] = os.getloadavg()[0]
    print(f"{'measure':<40s} {'value':>12s}")
    for key, value in rows.items():
        print(f"{key:<40s} {value:>12.3f}" if isinstance(value, float) else f"{key:<40s} {value:>12d}")
    print(
        "two scenes vs one rebuilt scene per frame: "
        f"{rows['frame_one_scene_rebuilt_s'] / rows['frame_two_scenes_s']:.1f}x"
    )
    atomic_write_json(RESULTS, rows)
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
