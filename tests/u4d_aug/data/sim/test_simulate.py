"""Simulated world (u4d_aug/data/sim): determinism, motion, pose consistency, layout, realism checks."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.distance import jensenshannon

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.data.formats import (
    read_calib,
    read_kitti_label,
    read_kitti_scan,
    read_nuscenes_scan,
    read_poses,
    read_times,
)
from u4d_aug.data.labels import SEMANTICKITTI_RAW_NAMES, map_semantickitti
from u4d_aug.data.sensors import hdl32, hdl64, intensity_response
from u4d_aug.data.sim import objects
from u4d_aug.data.sim.agents import _EgoLane
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import RAW, MeshBuilder, strip
from u4d_aug.data.sim.report import INTENSITY_BINS
from u4d_aug.data.sim.scenes import STREET_TYPES
from u4d_aug.data.sim.streets import Bend, Warp, lane_path, make_hills, make_network
from u4d_aug.data.sim.world import _add_mesh
from u4d_aug.data.sim.writer import (
    add_simulate_arguments,
    build_sequence,
    render_frame,
    run_simulate,
    simulate,
)
from u4d_aug.errors import InputError

TINY = REPO / "configs" / "sim" / "tiny.yaml"


def _tiny(*overrides: str) -> SimConfig:
    return load_config(SimConfig, TINY, overrides)


def _hashes(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "a"
    simulate(out, sequences=1, frames=3, seed=7, config=_tiny(), progress=False)
    return out


def test_raw_ids_are_semantickitti() -> None:
    for name, raw in RAW.items():
        assert SEMANTICKITTI_RAW_NAMES[raw] == name


def test_same_seed_byte_identical_and_resume(tiny_world: Path, tmp_path: Path) -> None:
    again = tmp_path / "b"
    simulate(again, sequences=1, frames=3, seed=7, config=_tiny(), progress=False)
    first = _hashes(tiny_world)
    assert first == _hashes(again)
    assert {"manifest.json", "sequences/00/poses.txt", "sequences/00/velodyne/000002.bin"} <= set(first)
    # a re-run resumes: a deleted frame is rewritten identically, the rest is skipped
    (again / "sequences/00/velodyne/000001.bin").unlink()
    summary = simulate(again, sequences=1, frames=3, seed=7, config=_tiny(), progress=False)
    assert summary["written"] == 1 and summary["skipped"] == 2
    assert _hashes(again) == first


def test_different_seed_differs(tiny_world: Path, tmp_path: Path) -> None:
    other = tmp_path / "c"
    simulate(other, sequences=1, frames=1, seed=8, config=_tiny(), progress=False)
    a = read_kitti_scan(tiny_world / "sequences/00/velodyne/000000.bin")
    b = read_kitti_scan(other / "sequences/00/velodyne/000000.bin")
    assert a.shape != b.shape or not np.array_equal(a, b)


def test_resume_with_other_settings_is_refused(tiny_world: Path) -> None:
    with pytest.raises(InputError, match="seed"):
        simulate(tiny_world, sequences=1, frames=3, seed=99, config=_tiny(), progress=False)


def test_layout_poses_times_labels(tiny_world: Path) -> None:
    seq = tiny_world / "sequences" / "00"
    poses = read_poses(seq / "poses.txt", read_calib(seq / "calib.txt"))
    built = build_sequence(7, 0, 3, hdl64(), _tiny())
    expected = np.linalg.inv(built.ego.poses[0]) @ built.ego.poses
    np.testing.assert_allclose(poses, expected, atol=1e-9)
    np.testing.assert_allclose(read_times(seq / "times.txt"), [0.0, 0.1, 0.2])
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * 10.0
    assert np.all((step > 4.5) & (step < 12.5)), step  # ego speed 5-12 m/s
    points = read_kitti_scan(seq / "velodyne" / "000000.bin")
    semantic, instance = read_kitti_label(seq / "labels" / "000000.label", len(points))
    assert points.dtype == np.float32 and points.shape[1] == 4
    assert points[:, 3].min() >= 0.0 and points[:, 3].max() <= 1.0
    assert set(np.unique(semantic).tolist()) <= set(SEMANTICKITTI_RAW_NAMES)
    r = np.linalg.norm(points[:, :3], axis=1)
    assert r.min() >= hdl64().min_range and r.max() <= hdl64().max_range
    # road under the sensor at about -sensor_height
    road = (semantic == 40) & (r < 15)
    assert abs(np.median(points[road, 2]) + 1.80) < 0.05
    # the labels stop at label_range (50 m), as in the real seq-00 frames
    assert np.all(semantic[r > 50.5] == 0) and np.all(instance[r > 50.5] == 0)
    assert np.mean(semantic[r < 49.5] == 0) < 0.01


def test_ring_major_storage_order() -> None:
    seq = build_sequence(3, 0, 1, hdl64(), _tiny())
    scan = render_frame(seq, 0)
    assert np.all(np.diff(scan.ring) >= 0)  # top ring first
    ring = scan.ring == 40
    azimuth = np.mod(np.arctan2(scan.points[ring, 1], scan.points[ring, 0]), 2 * np.pi)
    assert np.all(np.diff(azimuth) > -1e-3)  # counter-clockwise from the front


def test_moving_agents_move_and_keep_instance_ids() -> None:
    seq = build_sequence(11, 0, 3, hdl64(), _tiny("lidar.azimuth_steps=1024"))
    moving = [a for a in seq.agents if a.mesh.semantic[0] >= 252]
    assert moving
    for agent in moving:
        assert len(np.unique(agent.mesh.instance)) == 1 and agent.mesh.instance[0] > 0
        assert np.linalg.norm(agent.xy[1] - agent.xy[0]) > 0.05
    ids = [int(a.mesh.instance[0]) for a in seq.agents]
    assert len(set(ids)) == len(ids)
    scans = [render_frame(seq, f) for f in range(2)]
    seen = []
    for scan in scans:
        sel = scan.semantic >= 252
        seen.append(set(np.unique(scan.instance[sel]).tolist()))
        for inst in seen[-1]:  # one label per instance
            assert len(np.unique(scan.semantic[scan.instance == inst])) == 1
    assert seen[0] & seen[1], "a moving agent visible in both frames keeps its id"
    # the shared agents moved in the world between the frames
    for inst in seen[0] & seen[1]:
        agent = next(a for a in seq.agents if a.mesh.instance[0] == inst)
        assert np.linalg.norm(agent.xy[1] - agent.xy[0]) > 0.05


def test_static_points_align_with_poses(tmp_path: Path) -> None:
    out = tmp_path / "dense"
    simulate(out, 1, 3, seed=5, config=_tiny("lidar.azimuth_steps=2083"), progress=False)
    seq = out / "sequences" / "00"
    poses = read_poses(seq / "poses.txt", read_calib(seq / "calib.txt"))
    world = []
    for f in range(3):
        pts = read_kitti_scan(seq / "velodyne" / f"{f:06d}.bin")
        sem, _ = read_kitti_label(seq / "labels" / f"{f:06d}.label", len(pts))
        keep = (sem < 252) & (sem != 30) & (np.linalg.norm(pts[:, :3], axis=1) < 40)
        xyz = pts[keep, :3].astype(np.float64)
        world.append(xyz @ poses[f][:3, :3].T + poses[f][:3, 3])
    # frame 1 against its neighbours 0 and 2: ground rings sweep ~1 m per frame, so one neighbour alone leaves
    # gaps of half a ring spacing (the real seq-00 scans give 5.4 cm for 1 -> 0 in SOURCES.md)
    dist, _ = cKDTree(np.concatenate([world[0], world[2]])).query(world[1])
    assert np.median(dist) <= 0.05, np.median(dist)
    # a 10 cm pose error (height: most points are ground, which hides horizontal shifts) is clearly visible
    shifted, _ = cKDTree(np.concatenate([world[0], world[2]])).query(world[1] + [0.0, 0.0, 0.1])
    assert np.median(shifted) > np.median(dist) + 0.02


def test_cli_arguments(tmp_path: Path, capsys, caplog) -> None:
    caplog.set_level(logging.INFO, logger="u4d_aug.data.sim.writer")
    parser = argparse.ArgumentParser()
    add_simulate_arguments(parser)
    args = parser.parse_args(
        [
            "--out",
            str(tmp_path / "cli"),
            "--frames",
            "1",
            "--seed",
            "2",
            "--config",
            str(TINY),
            "--set",
            "agents.pedestrians_per_100m=0",
        ]
    )
    assert run_simulate(args) == 0
    assert "wrote 1 frames" in capsys.readouterr().out
    # it says which preset wrote the world, and records it
    said = f"world of {TINY}, overrides agents.pedestrians_per_100m=0 (recorded in manifest.json)"
    assert any(said in message for message in caplog.messages), caplog.messages
    manifest = json.loads((tmp_path / "cli" / "manifest.json").read_text())
    assert manifest["config_source"] == {"config": str(TINY), "overrides": ["agents.pedestrians_per_100m=0"]}
    with pytest.raises(InputError, match="unknown config key"):
        load_config(SimConfig, None, ["lidar.nope=1"])


def test_streets_bend_within_limits() -> None:
    cfg = _tiny("street.straight_prob=0")
    warp = make_network(np.random.default_rng(3), cfg.street, 400.0).warp
    s = np.linspace(-400.0, 400.0, 8001)
    for bend in (warp.bend_x, warp.bend_y):
        slope = bend.slope(s)
        np.testing.assert_allclose(np.gradient(bend(s), s), slope, atol=1e-3)
        assert np.ptp(np.degrees(np.arctan(slope))) > 10.0  # the streets genuinely change direction
        assert np.abs(slope).max() <= cfg.street.bend_max_slope + 1e-9
        curvature = np.abs(np.gradient(slope, s)) / (1.0 + slope**2) ** 1.5
        assert curvature.max() <= 1.0 / cfg.street.bend_min_radius + 1e-4
    straight = make_network(np.random.default_rng(3), _tiny("street.straight_prob=1").street, 400.0).warp
    xy = np.random.default_rng(0).uniform(-300, 300, (100, 2))
    np.testing.assert_array_equal(straight.points(xy), xy)


def test_hills_gradient_and_limits() -> None:
    cfg = _tiny("street.flat_prob=0")
    xy = np.random.default_rng(0).uniform(-400, 400, (2000, 2))
    for seed in range(5):
        hills = make_hills(np.random.default_rng(seed), cfg.street)
        eps = 1e-3
        numeric = np.stack(
            [
                (hills(xy + [eps, 0]) - hills(xy - [eps, 0])) / (2 * eps),
                (hills(xy + [0, eps]) - hills(xy - [0, eps])) / (2 * eps),
            ],
            axis=-1,
        )
        np.testing.assert_allclose(hills.gradient(xy), numeric, atol=1e-6)
        grade = np.linalg.norm(hills.gradient(xy), axis=1)
        assert grade.max() <= cfg.street.hill_max_grade + 1e-9
        assert np.ptp(hills(xy)) > 1.0  # genuinely hilly over a few hundred metres
        assert np.sum(np.abs(hills.amplitude) * np.linalg.norm(hills.wavevector, axis=1) ** 2) <= (
            1.0 / cfg.street.hill_min_radius + 1e-12
        )
    flat = make_hills(np.random.default_rng(0), _tiny("street.flat_prob=1").street)
    assert np.all(flat(xy) == 0.0)


def test_ego_rides_the_hills() -> None:
    seq = build_sequence(2, 0, 20, hdl64(), _tiny("street.flat_prob=0"))
    hills = seq.world.network.warp.hills
    poses, xy = seq.ego.poses, seq.ego.xy
    assert np.ptp(hills(seq.ego.route_xy)) > 0.3  # the route climbs or descends
    np.testing.assert_allclose(poses[:, 2, 3], hills(xy) + seq.cfg.lidar.sensor_height, atol=0.02)
    # the body's up axis is normal to the ground (up to the sensor mount tilt, std 0.3 deg)
    grade = hills.gradient(xy)
    normal = np.column_stack([-grade, np.ones(len(grade))])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", poses[:, :3, 2], normal)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.5
    # the road around the sensor (within 8 m: beyond, the lane camber lowers it) lies at -sensor_height
    for frame in (0, 19):
        scan = render_frame(seq, frame)
        r = np.linalg.norm(scan.points[:, :3], axis=1)
        road = (scan.semantic == RAW["road"]) & (r < 8)
        assert abs(np.median(scan.points[road, 2]) + seq.cfg.lidar.sensor_height) < 0.05


def test_warp_bends_surfaces_and_carries_objects_rigidly() -> None:
    warp = Warp(Bend(np.array([10.0]), np.array([2 * np.pi / 200]), np.array([0.0])), Bend(*np.zeros((3, 0))))
    mb = MeshBuilder(warp)
    mb.axis = 0  # objects belong to the x-street
    xs = np.linspace(0.0, 100.0, 51)
    band = strip(np.column_stack([xs, np.full(51, 5.0)]), np.column_stack([xs, np.full(51, 8.0)]), 0.1)
    mb.add(band, "sidewalk", "paving", 0.3)
    car = objects.place(objects.car(np.random.default_rng(0), "car", 5), 0.0, (25.0, 3.0, 0.0))
    _add_mesh(mb, car)
    mesh = mb.build()
    n = len(band[0])
    # surfaces follow the bent street point by point
    np.testing.assert_allclose(mesh.vertices[:n, :2], warp.points(band[0][:, :2]), atol=1e-4)
    # the car keeps its shape and turns with the street: heading atan(df/dx) at its centre, 12.5 deg
    moved = mesh.vertices[n:].astype(np.float64)
    original = car.vertices.astype(np.float64)
    np.testing.assert_allclose(moved[:, 2], original[:, 2], atol=1e-5)
    pairs = np.random.default_rng(1).integers(0, len(original), (200, 2))
    dist = np.linalg.norm(moved[pairs[:, 0]] - moved[pairs[:, 1]], axis=1)
    np.testing.assert_allclose(dist, np.linalg.norm(original[pairs[:, 0]] - original[pairs[:, 1]], axis=1), atol=1e-4)
    axis = np.linalg.svd(moved[:, :2] - moved[:, :2].mean(axis=0), full_matrices=False)[2][0]
    heading = np.degrees(np.arctan2(axis[1], axis[0])) % 180.0
    expected = np.degrees(np.arctan(10.0 * 2 * np.pi / 200 * np.cos(2 * np.pi * 25.0 / 200)))
    assert abs(heading - expected) < 0.5, (heading, expected)


def test_ego_and_agents_drive_the_bent_streets() -> None:
    seq = build_sequence(4, 0, 30, hdl64(), _tiny("street.straight_prob=0"))
    warp = seq.world.network.warp
    np.testing.assert_allclose(seq.ego.route_xy, warp.points(seq.ego.route_lattice))
    lattice_heading = np.arctan2(*np.diff(seq.ego.route_lattice, axis=0).T[::-1])
    world_heading = np.arctan2(*np.diff(seq.ego.route_xy, axis=0).T[::-1])
    assert np.abs(np.angle(np.exp(1j * (world_heading - lattice_heading)))).max() > np.radians(3.0)
    step = np.linalg.norm(np.diff(seq.ego.xy, axis=0), axis=1) * 10.0
    assert np.all((step > 4.5) & (step < 12.5)), step  # speeds hold on the curves
    # the ego stays on its lane: the ground just ahead of and behind the sensor is carriageway in every frame
    for frame in (0, 29):
        scan = render_frame(seq, frame)
        x, y, z = scan.points[:, :3].T
        lane = (np.abs(y) < 1.0) & (np.abs(x) > 4.0) & (np.abs(x) < 8.0) & (z < -1.6)
        assert lane.sum() > 100
        assert np.isin(scan.semantic[lane], [RAW["road"], RAW["lane-marking"]]).mean() > 0.95
    vehicles = [a for a in seq.agents if a.kind != "person"]
    assert vehicles
    for agent in vehicles:  # heading follows the path tangent, also on the curves
        motion = np.diff(agent.xy, axis=0)
        moving = np.linalg.norm(motion, axis=1) > 0.2
        direction = np.arctan2(motion[moving, 1], motion[moving, 0])
        mid = np.angle(np.exp(1j * agent.yaw[1:]) + np.exp(1j * agent.yaw[:-1]))[moving]
        assert np.abs(np.angle(np.exp(1j * (direction - mid)))).max() < np.radians(8.0)


def test_ego_keeps_clear_of_parked_cars_on_its_right() -> None:
    net = make_network(np.random.default_rng(0), SimConfig().street, 200.0)
    j = len(net.ys) // 2
    line = net.ys[j]
    line.lanes_per_direction, line.lane_width = 1, 4.0
    nodes = [(0, j), (1, j), (2, j)]  # straight along +x: the negative side (index 0) is on the right
    ego = _EgoLane(center_bias=0.4, parked_clearance=0.8)
    offsets = {}
    for parking in ((2.2, 0.0), (0.0, 2.2)):
        line.parking = parking
        path, turning = lane_path(net, nodes, ego)
        assert not turning.any()
        offsets[parking] = line.position - path[:, 1]  # metres right of the centre line
    # rightmost lane centre 2.0 m, pulled 40 % towards the centre: 1.2 m; parked cars on the right: 0.8 m more
    np.testing.assert_allclose(offsets[(0.0, 2.2)], 1.2, atol=1e-9)
    np.testing.assert_allclose(offsets[(2.2, 0.0)], 0.4, atol=1e-9)
    # main streets keep their inner lane; the pull never crosses the centre line
    assert _EgoLane(0.4, 5.0)(line, 1) == 0.0
    line.lanes_per_direction = 2
    assert _EgoLane(0.4, 0.8)(line, 1) == 2.0


@pytest.mark.slow
def test_default_hdl64_frame_point_count() -> None:
    seq = build_sequence(0, 0, 1, hdl64(), SimConfig())
    scan = render_frame(seq, 0)
    assert 100_000 <= len(scan.points) <= 135_000, len(scan.points)


@pytest.mark.slow
def test_four_sequences_cover_fifteen_classes(tmp_path: Path) -> None:
    cfg = SimConfig()
    present = set()
    for index in range(4):
        seq = build_sequence(1, index, 6, hdl64(), cfg)
        for frame in (0, 5):
            present |= set(np.unique(map_semantickitti(render_frame(seq, frame).semantic)).tolist())
    present.discard(19)
    assert len(present) >= 15, sorted(present)


def _instances(mesh, label: str) -> int:
    return len(np.unique(mesh.instance[mesh.semantic == RAW[label]]))


def test_sidewalk_bicycles_only_when_asked() -> None:
    off = build_sequence(4, 0, 3, hdl64(), _tiny()).world.mesh
    on = build_sequence(4, 0, 3, hdl64(), _tiny("objects.sidewalk_bicycle_prob=1.0")).world.mesh
    assert _instances(on, "bicycle") >= _instances(off, "bicycle") + 10
    # every bicycle is a rigid ~1.8 m object standing on the ground, not floating or buried
    for inst in np.unique(on.instance[on.semantic == RAW["bicycle"]]):
        v = on.vertices[np.unique(on.triangles[(on.instance == inst) & (on.semantic == RAW["bicycle"])])]
        assert 1.3 < np.ptp(v[:, :2], axis=0).max() < 2.2 and 0.8 < np.ptp(v[:, 2]) < 1.4


def test_rich_preset_makes_rare_classes_frequent() -> None:
    rich = load_config(SimConfig, REPO / "configs" / "sim" / "seg_rich.yaml", [])
    counts = {"default": {}, "rich": {}}
    for name, cfg in (("default", SimConfig()), ("rich", rich)):
        for index in range(3):
            seq = build_sequence(5, index, 3, hdl64(), cfg)
            for label in ("truck", "other-vehicle", "motorcycle", "bicycle"):
                counts[name][label] = counts[name].get(label, 0) + _instances(seq.world.mesh, label)
            for agent in seq.agents:
                counts[name][agent.kind] = counts[name].get(agent.kind, 0) + 1
    for key in ("truck", "other-vehicle", "motorcycle", "bicycle", "person", "bicyclist", "motorcyclist"):
        assert counts["rich"].get(key, 0) > 1.5 * counts["default"].get(key, 0), (key, counts)


def test_manifest_records_the_preset_and_the_street_types(tmp_path: Path) -> None:
    import json

    parser = argparse.ArgumentParser()
    add_simulate_arguments(parser)
    out = tmp_path / "varied"
    args = parser.parse_args(["--out", str(out), "--frames", "1", "--sequences", "3", "--config", "sim/varied"])
    args.overrides = ["view_radius=60", "lidar.azimuth_steps=360"]
    assert run_simulate(args) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config_source"] == {"config": "sim/varied", "overrides": args.overrides}
    assert manifest["config"]["street_types"]["park"] > 0
    assert len(manifest["street_types"]) == 3 and set(manifest["street_types"]) <= set(STREET_TYPES)


def test_resume_of_a_world_written_before_the_street_types(tmp_path: Path) -> None:
    import json

    out = tmp_path / "old"
    simulate(out, 1, 1, seed=2, config=_tiny(), progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    for section, key in (("street", "main_lanes"), ("lots", "driveway_prob"), ("agents", "agent_route_extra")):
        del manifest["config"][section][key]  # as main wrote it
    del manifest["config"]["street_types"]
    (out / "manifest.json").write_text(json.dumps(manifest))
    assert simulate(out, 1, 1, seed=2, config=_tiny(), progress=False)["skipped"] == 1
    with pytest.raises(InputError, match="'config' differs"):
        simulate(out, 1, 1, seed=2, config=_tiny("lots.driveway_prob=0.5"), progress=False)


def _identity(sensor):
    return dataclasses.replace(sensor, intensity_floor=0.0, intensity_gain=1.0, intensity_gamma=1.0)


def _hdl32_remission(sensor, places: int = 2) -> list:
    """Scans of `places` tiny places x 1 frame (seed 5) seen by `sensor`."""
    return [render_frame(build_sequence(5, k, 1, sensor, _tiny()), 0) for k in range(places)]


def test_intensity_response_changes_the_intensity_and_nothing_else() -> None:
    fitted, plain = _hdl32_remission(hdl32(), 1)[0], _hdl32_remission(_identity(hdl32()), 1)[0]
    np.testing.assert_array_equal(fitted.points[:, :3], plain.points[:, :3])  # same random numbers, same returns
    np.testing.assert_array_equal(fitted.semantic, plain.semantic)
    np.testing.assert_array_equal(fitted.points[:, 3], intensity_response(hdl32(), plain.points[:, 3]))
    assert np.median(fitted.points[:, 3]) < 0.1 < np.median(plain.points[:, 3])


def test_hdl32_remission_moves_towards_the_real_nuscenes_keyframe(real_root: Path) -> None:
    scan = next((real_root / "nuscenes_mmdet3d_demo").glob("**/LIDAR_TOP/*.pcd.bin"))

    def hist(values: np.ndarray) -> np.ndarray:
        bins = np.clip(np.searchsorted(INTENSITY_BINS, values, side="right") - 1, 0, len(INTENSITY_BINS) - 2)
        return np.bincount(bins, minlength=len(INTENSITY_BINS) - 1)

    real = hist(read_nuscenes_scan(scan).points[:, 3])
    js = {
        name: jensenshannon(hist(np.concatenate([s.points[:, 3] for s in _hdl32_remission(sensor)])), real, base=2)
        for name, sensor in (("identity", _identity(hdl32())), ("fitted", hdl32()))
    }
    assert js["identity"] > 0.6 and js["fitted"] < 0.3, js


def test_resume_of_an_hdl32_world_written_before_the_intensity_response_is_refused(tmp_path: Path) -> None:
    import json

    out = tmp_path / "old32"
    simulate(out, 1, 1, seed=2, sensor="hdl32", config=_tiny(), progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["sensor_intensity_response"] == [0.009, 1.08, 2.68]
    del manifest["sensor_intensity_response"]  # as main wrote it: the HDL-32E reported the remission
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="'sensor_intensity_response' differs"):
        simulate(out, 1, 1, seed=2, sensor="hdl32", config=_tiny(), progress=False)
