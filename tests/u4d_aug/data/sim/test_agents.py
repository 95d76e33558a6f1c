"""Ego and agents of the simulated world (u4d_aug/data/sim/agents.py): the ego on its lane, over the hills and round
the bends, moving agents keep their ids and follow their paths, speeds brake for turns, bodies sit on the slope."""

from __future__ import annotations

import numpy as np

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.data.sensors import hdl64
from u4d_aug.data.sim.agents import _EgoLane, on_slope, speed_profile
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import RAW
from u4d_aug.data.sim.streets import lane_path, make_network
from u4d_aug.data.sim.writer import build_sequence, render_frame

TINY = REPO / "configs" / "sim" / "tiny.yaml"


def _tiny(*overrides: str) -> SimConfig:
    return load_config(SimConfig, TINY, overrides)


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


def test_bodies_sit_on_the_slope_with_x_forward_and_z_normal_to_the_ground():
    yaw = np.array([0.0, 0.0, 1.0])
    grade = np.array([(0.0, 0.0), (0.1, 0.0), (0.03, -0.05)])
    rotations = on_slope(yaw, grade)
    for rotation in rotations:
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(rotation), 1.0)
    np.testing.assert_allclose(rotations[0], np.eye(3), atol=1e-12)  # flat ground, heading +x
    np.testing.assert_allclose(rotations[1][:, 0], np.array([1.0, 0.0, 0.1]) / np.hypot(1.0, 0.1))  # up the slope
    normal = np.array([-0.03, 0.05, 1.0])
    np.testing.assert_allclose(rotations[2][:, 2], normal / np.linalg.norm(normal), atol=1e-12)
    assert np.isclose(np.arctan2(rotations[2][1, 0], rotations[2][0, 0]), 1.0)  # the heading seen from above


def test_speed_profile_brakes_for_turns_within_its_deceleration():
    path_s = np.arange(0.0, 400.0, 0.05)
    turning = ((path_s >= 100.0) & (path_s < 110.0)).astype(np.int8)
    dt, accel = 0.1, 1.5
    s = speed_profile(np.random.default_rng(0), path_s, turning, 300, dt, (10.0, 10.0), 3.0, accel)
    speed = np.diff(s) / dt
    assert s[0] == 0.0 and np.all(speed > 0) and speed.max() <= 10.0 + 1e-9
    assert np.all(np.diff(speed) >= -accel * dt - 1e-9)  # no harder braking than `accel`
    in_turn = (s[:-1] >= 100.0) & (s[:-1] < 110.0)
    assert in_turn.any() and speed[in_turn].max() <= 3.0 + accel * dt + 1e-9
    cruise = speed_profile(np.random.default_rng(0), path_s, np.zeros_like(turning), 20, dt, (8.0, 8.0), 3.0, accel)
    np.testing.assert_allclose(cruise, 0.8 * np.arange(20))  # no turn ahead: steady at the cruise speed
