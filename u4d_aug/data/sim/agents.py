"""Ego motion and moving agents of a simulated sequence: trajectories for every frame, posed meshes per frame.

The ego drives a lane of the street lattice at 5-12 m/s (10 Hz), slowing for turns. Cars, vans, trucks,
motorcyclists and bicyclists follow their own lane routes; pedestrians walk the sidewalk loops of blocks with
swinging legs. Lane paths are planned on the straight lattice and bent by the network's warp before the speed
profile, so speeds hold along the curved streets. Agents that would overlap the ego or an earlier agent in
any frame are rejected, so occlusion is all that couples them. Every agent keeps one instance id for the whole sequence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from u4d_aug.data.sim import objects
from u4d_aug.data.sim.config import AgentConfig, SimConfig
from u4d_aug.data.sim.geometry import TriangleMesh, concat_meshes
from u4d_aug.data.sim.streets import Hills, Line, Network, arc_length, lane_path, plan_route, sample_path
from u4d_aug.data.sim.world import World


@dataclass
class Agent:
    """A moving (or standing) object: local mesh, limb part ids, and its pose in every frame."""

    kind: str
    mesh: TriangleMesh  # local frame, x forward
    parts: np.ndarray  # (V,) limb id per vertex (objects.PART_*)
    xy: np.ndarray  # (F, 2) world position per frame
    yaw: np.ndarray  # (F,) heading per frame
    z: float  # ground height under the agent
    travelled: np.ndarray  # (F,) metres walked/driven (gait phase)
    half_extent: tuple[float, float]  # footprint half length/width for the overlap test


@dataclass
class EgoMotion:
    """Ego LiDAR poses (F, 4, 4) world <- sensor and the planar trajectory."""

    poses: np.ndarray
    xy: np.ndarray  # (F, 2)
    yaw: np.ndarray  # (F,)
    route_xy: np.ndarray  # (K, 2) dense lane path, world coordinates
    route_lattice: np.ndarray  # (K, 2) the same path on the straight lattice (for building the world around it)


def _rightmost_lane(line: Line, side: int) -> float:
    return line.half_road - line.lane_width / 2


@dataclass
class _EgoLane:
    """Ego lane offset: rightmost lane, pulled towards the centre on one-lane-per-direction streets, and by
    `parked_clearance` more where a parking strip lines the right of the lane."""

    center_bias: float
    parked_clearance: float

    def __call__(self, line: Line, side: int) -> float:
        if line.lanes_per_direction == 1:
            offset = _rightmost_lane(line, side) * (1.0 - self.center_bias)
            if line.parking[side] > 0:
                offset = max(offset - self.parked_clearance, 0.0)
            return offset
        return line.lane_width / 2  # inner lane of a main street: parked cars stay a lane away


def _bike_lane(line: Line, side: int) -> float:
    return line.half_road - 0.75


def speed_profile(rng, path_s, turning, frames, dt, speed_range, turn_speed, accel, start_s=0.0):
    """Arc length per frame: random cruise speeds, braking to `turn_speed` before turn arcs."""
    turn_starts = path_s[1:][np.diff(turning) > 0]
    turn_s = path_s[turning > 0]
    s, v = start_s, float(rng.uniform(*speed_range))
    cruise, next_change = v, float(rng.uniform(4.0, 10.0))
    out = np.empty(frames)
    for k in range(frames):
        out[k] = s
        t = k * dt
        if t >= next_change:
            cruise, next_change = float(rng.uniform(*speed_range)), t + float(rng.uniform(4.0, 10.0))
        allowed = cruise
        ahead = turn_starts[turn_starts >= s]
        if len(ahead):
            allowed = min(allowed, float(np.sqrt(turn_speed**2 + 2 * accel * (ahead[0] - s))))
        if len(turn_s) and np.any(np.abs(turn_s - s) < 0.5):
            allowed = min(allowed, turn_speed)
        v += float(np.clip(allowed - v, -accel * dt, accel * dt))
        v = max(v, 0.5)
        s += v * dt
    return out


def ego_motion(rng: np.random.Generator, net: Network, cfg: SimConfig, frames: int) -> EgoMotion:
    """Ego route and poses: the sensor sits `lidar.sensor_height` above the road, the body follows its slope."""
    ac = cfg.agents
    dt = 1.0 / cfg.frame_rate
    i0 = int(np.argmin([abs(line.position) for line in net.xs]))
    j0 = int(np.argmin([abs(line.position) for line in net.ys]))
    heading = int(rng.integers(4))
    length = frames * ac.ego_speed[1] * dt + 150.0
    nodes = plan_route(rng, net, (i0, j0), heading, length, ac.ego_turn_prob)
    lattice, turning = lane_path(
        net,
        nodes,
        _EgoLane(ac.ego_center_bias, ac.ego_parked_clearance),
        start_fraction=float(rng.uniform(0.2, 0.6)),
    )
    path = net.warp.points(lattice)
    s = arc_length(path)
    at = speed_profile(rng, s, turning, frames, dt, ac.ego_speed, ac.ego_turn_speed, ac.ego_accel)
    xy, yaw = sample_path(path, s, at)
    # slow wander within the lane
    phase, wavelength = rng.uniform(0, 2 * np.pi), rng.uniform(30.0, 60.0)
    lateral = ac.ego_lateral_jitter * np.sin(2 * np.pi * at / wavelength + phase)
    xy = xy + lateral[:, None] * np.column_stack([-np.sin(yaw), np.cos(yaw)])
    poses = np.tile(np.eye(4), (frames, 1, 1))
    hills = net.warp.hills
    grade = np.zeros_like(xy) if hills is None else hills.gradient(xy)
    poses[:, :3, :3] = on_slope(yaw, grade)
    poses[:, :2, 3] = xy
    poses[:, 2, 3] = cfg.lidar.sensor_height + (0.0 if hills is None else hills(xy))
    pitch, roll = np.radians(rng.normal(0.0, cfg.lidar.mount_tilt_deg, 2))
    roll += np.arctan(ac.lane_camber)  # the lane slopes down to the curb: the car leans right
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    tilt = np.eye(4)
    tilt[:3, :3] = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return EgoMotion(poses @ tilt, xy, yaw, path, lattice)


def on_slope(yaw: np.ndarray, grade: np.ndarray) -> np.ndarray:
    """(F, 3, 3) body rotations heading `yaw` (F,) on ground of grade (F, 2): x forward, z normal to the ground."""
    c, s = np.cos(yaw), np.sin(yaw)
    forward = np.column_stack([c, s, grade[:, 0] * c + grade[:, 1] * s])
    left = np.column_stack([-s, c, -grade[:, 0] * s + grade[:, 1] * c])
    x = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    z = np.cross(x, left)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=2)


def _overlap(xy_a, yaw_a, ext_a, xy_b, yaw_b, ext_b, margin: float) -> bool:
    """Oriented-rectangle overlap in any frame (separating axis test, vectorised over frames)."""
    d = xy_b - xy_a
    axes = [np.column_stack([np.cos(y), np.sin(y)]) for y in (yaw_a, yaw_a + np.pi / 2, yaw_b, yaw_b + np.pi / 2)]
    separated = np.zeros(len(d), dtype=bool)
    for axis in axes:
        proj = np.abs(np.einsum("ij,ij->i", d, axis))
        ra = (ext_a[0] + margin) * np.abs(np.einsum("ij,ij->i", axes[0], axis)) + (ext_a[1] + margin) * np.abs(
            np.einsum("ij,ij->i", axes[1], axis)
        )
        rb = ext_b[0] * np.abs(np.einsum("ij,ij->i", axes[2], axis)) + ext_b[1] * np.abs(
            np.einsum("ij,ij->i", axes[3], axis)
        )
        separated |= proj > ra + rb
    return not bool(separated.all())


def _vehicle(rng, kind: str, instance: int):
    if kind == "car":
        mesh = objects.car(rng, "moving-car", instance, kind=str(rng.choice(["sedan", "hatch", "suv"])))
        ext = (2.4, 0.95)
    elif kind == "truck":
        mesh, ext = objects.truck(rng, "moving-truck", instance), (5.0, 1.25)
    elif kind == "van":
        mesh, ext = objects.van(rng, "moving-other-vehicle", instance), (3.0, 1.05)
    elif kind == "motorcyclist":
        mesh, ext = objects.rider(rng, "moving-motorcyclist", instance, motor=True)[0], (1.1, 0.45)
    else:
        mesh, ext = objects.rider(rng, "moving-bicyclist", instance, motor=False)[0], (0.9, 0.4)
    return mesh, ext


def make_agents(rng: np.random.Generator, world: World, ego: EgoMotion, cfg: SimConfig) -> list[Agent]:
    """Moving vehicles, riders and pedestrians near the ego route, free of overlap with ego and each other."""
    ac: AgentConfig = cfg.agents
    net = world.network
    frames = len(ego.xy)
    dt = 1.0 / cfg.frame_rate
    route_len = float(arc_length(ego.route_xy)[-1])
    instance = world.next_instance
    agents: list[Agent] = []
    ego_ext = (4.5, 1.0)  # keeps followers/leaders a few metres away, not only non-overlapping
    near_nodes = _nodes_near(net, ego.xy, 90.0)
    counts = {
        "car": ac.cars_per_100m,
        "truck": ac.trucks_per_100m,
        "van": ac.vans_per_100m,
        "motorcyclist": ac.motorcyclists_per_100m,
        "bicyclist": ac.bicyclists_per_100m,
    }
    speeds = {
        "car": ac.car_speed,
        "truck": ac.car_speed,
        "van": ac.car_speed,
        "motorcyclist": ac.motorcyclist_speed,
        "bicyclist": ac.bicyclist_speed,
    }
    for kind, density in counts.items():
        n = int(rng.poisson(density * route_len / 100.0))
        for _ in range(n):
            start = near_nodes[int(rng.integers(len(near_nodes)))]
            heading = int(rng.integers(4))
            speed = speeds[kind]
            nodes = plan_route(rng, net, start, heading, frames * speed[1] * dt + ac.agent_route_extra, 0.4)
            if len(nodes) < 3:
                continue
            offset = _bike_lane if kind == "bicyclist" else _rightmost_lane
            lattice, turning = lane_path(net, nodes, offset, start_fraction=float(rng.uniform(0.0, 1.0)))
            path = net.warp.points(lattice)
            s = arc_length(path)
            at = speed_profile(rng, s, turning, frames, dt, speed, min(speed[0], 4.0), 2.0)
            xy, yaw = sample_path(path, s, at)
            mesh, ext = _vehicle(rng, kind, instance)
            if _overlap(ego.xy, ego.yaw, ego_ext, xy, yaw, ext, 0.8) or any(
                _overlap(a.xy, a.yaw, a.half_extent, xy, yaw, ext, 0.5) for a in agents if a.z == 0.0
            ):
                continue
            agents.append(Agent(kind, mesh, np.zeros(len(mesh.vertices), np.int64), xy, yaw, 0.0, at, ext))
            instance += 1
    blocks = [b for b in world.blocks if _min_dist(b.walk_loop, ego.xy) < 70.0]
    n_people = int(rng.poisson(ac.pedestrians_per_100m * route_len / 100.0)) if blocks else 0
    for _ in range(n_people):
        block = blocks[int(rng.integers(len(blocks)))]
        walk, lift = block.walk_loop, 0.0
        if block.paths:  # parks, squares, parking lots: their own walks too (lot blocks draw nothing here)
            k = int(rng.integers(len(block.paths) + 1))
            walk, lift = (block.walk_loop, 0.0) if k == 0 else (block.paths[k - 1], 0.05)
        loop = walk if rng.random() < 0.5 else walk[::-1]
        standing = rng.random() < ac.standing_person_prob
        speed = 0.0 if standing else float(rng.uniform(*ac.pedestrian_speed))
        closed = np.concatenate([loop, loop[:1]])
        s_loop = arc_length(closed)
        reps = int(np.ceil(speed * frames * dt / s_loop[-1])) + 2
        path = np.concatenate([closed[:-1]] * reps + [closed[:1]])
        s = arc_length(path)
        at = float(rng.uniform(0, s_loop[-1])) + speed * dt * np.arange(frames)
        xy, yaw = sample_path(path, s, at)
        xy = xy + rng.normal(0.0, 0.25, 2)  # people do not all walk on one line
        mesh, parts = objects.person(rng, "person" if standing else "moving-person", instance)
        agents.append(Agent("person", mesh, parts, xy, yaw, world.network.curb_height + lift, at, (0.3, 0.3)))
        instance += 1
    return agents


def _nodes_near(net: Network, xy: np.ndarray, radius: float) -> list[tuple[int, int]]:
    pts = xy[:: max(1, len(xy) // 200)]
    out = []
    for i in range(1, len(net.xs) - 2):
        for j in range(1, len(net.ys) - 2):
            if np.min(np.linalg.norm(pts - net.warp.points(net.node(i, j)), axis=1)) < radius:
                out.append((i, j))
    return out or [(len(net.xs) // 2, len(net.ys) // 2)]


def _min_dist(points: np.ndarray, xy: np.ndarray) -> float:
    sub = xy[:: max(1, len(xy) // 100)]
    return float(np.min(np.linalg.norm(points[:, None, :] - sub[None], axis=2)))


def _limb_pose(agent: Agent, frame: int) -> np.ndarray:
    """Local vertices with legs/arms swung about their top joints (walking gait, stride ~1.4 m)."""
    vertices = agent.mesh.vertices.astype(np.float64)
    if not np.any(agent.parts):
        return vertices
    phase = 2 * np.pi * agent.travelled[frame] / 1.4
    swing = 0.0 if agent.travelled[-1] == agent.travelled[0] else 0.45 * np.sin(phase)
    out = vertices.copy()
    for part, sign in (
        (objects.PART_LEFT_LEG, 1.0),
        (objects.PART_RIGHT_LEG, -1.0),
        (objects.PART_LEFT_ARM, -0.6),
        (objects.PART_RIGHT_ARM, 0.6),
    ):
        sel = agent.parts == part
        if not sel.any():
            continue
        pivot_z = vertices[sel, 2].max()
        a = swing * sign
        dx, dz = vertices[sel, 0], vertices[sel, 2] - pivot_z
        out[sel, 0] = dx * np.cos(a) - dz * np.sin(a)
        out[sel, 2] = pivot_z + dx * np.sin(a) + dz * np.cos(a)
    return out


def dynamic_mesh(
    agents: list[Agent], frame: int, ego_xy: np.ndarray, radius: float, hills: Hills | None = None
) -> TriangleMesh:
    """All agents within `radius` of the ego, posed for `frame`, as one mesh (on the `hills` ground if given)."""
    meshes = []
    for agent in agents:
        if np.linalg.norm(agent.xy[frame] - ego_xy) > radius:
            continue
        local = _limb_pose(agent, frame)
        c, s = np.cos(agent.yaw[frame]), np.sin(agent.yaw[frame])
        world = np.empty_like(local)
        world[:, 0] = c * local[:, 0] - s * local[:, 1] + agent.xy[frame, 0]
        world[:, 1] = s * local[:, 0] + c * local[:, 1] + agent.xy[frame, 1]
        world[:, 2] = local[:, 2] + agent.z
        if hills is not None:  # point by point: the body follows the local grade (a few cm over its length)
            world[:, 2] += hills(world[:, :2])
        m = agent.mesh
        meshes.append(
            TriangleMesh(world.astype(np.float32), m.triangles, m.semantic, m.instance, m.material, m.reflectivity)
        )
    return concat_meshes(meshes)
