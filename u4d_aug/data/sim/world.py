"""Static world of one simulated sequence: roads, curbs, sidewalks, lots, buildings, vegetation, furniture.

Everything within `view_radius` of the ego route is built into one labelled triangle mesh (numpy only); the
ray caster adds it to an open3d RaycastingScene once per sequence. Layout follows a KITTI residential street:
carriageway, parking strips, curb, sidewalk (sometimes with a grass strip and street trees), then lots.
Blocks are laid out on the straight lattice and bent into the world by the network's warp as parts are added
(streets.Warp): long surfaces are tessellated finely enough (<= 2-4 m) to follow the curves.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from u4d_aug.data.sim import blocks, objects
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import (
    MeshBuilder,
    TriangleMesh,
    add_mesh,
    box,
    concat_meshes,
    densify,
    flat_grid,
    grid_surface,
    merge,
    polygon_fan,
    quad,
    sample_reflectivity,
    strip,
    transform,
    wall_strip,
)
from u4d_aug.data.sim.streets import Network

# block sides: 0 bottom (-y), 1 right (+x), 2 top (+y), 3 left (-x); u runs counter-clockwise, n points inward
_SIDE_U = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
_SIDE_N = np.array([[0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0]])
MARK_Z, PARK_Z = 0.004, 0.002  # overlays sit a few mm above the carriageway (no coplanar hits)
STEP = 2.0  # m, longest edge of outlines that the warp bends (curbs, sidewalk edges, markings)


@dataclass
class Block:
    """One city block: curb rectangle, inner (lot) rectangle and the pedestrians' walking loop."""

    index: tuple[int, int]
    curb: tuple[float, float, float, float]  # x0, y0, x1, y1 at the curb line, lattice coordinates
    inner: tuple[float, float, float, float]  # lot rectangle, lattice coordinates
    walk_loop: np.ndarray  # (K, 2) closed polyline on the sidewalk, counter-clockwise, world coordinates
    paths: list[np.ndarray] = field(default_factory=list)  # more closed walks (parks, squares), world coordinates


@dataclass
class World:
    """Static mesh plus what the agents need: the network, blocks, and the next free instance id."""

    mesh: TriangleMesh
    network: Network
    blocks: list[Block]
    next_instance: int


class _Ids:
    def __init__(self) -> None:
        self.next = 1

    def take(self) -> int:
        self.next += 1
        return self.next - 1


def _terrain_height(rng: np.random.Generator):
    """Smooth ground undulation (a few cm) as a closure-free callable object."""
    freqs = rng.normal(0.0, 0.35, (4, 2))
    phases = rng.uniform(0, 2 * np.pi, 4)
    return _Undulation(freqs, phases)


@dataclass
class _Undulation:
    freqs: np.ndarray
    phases: np.ndarray
    amplitude: float = 0.04

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        arg = x[..., None] * self.freqs[:, 0] + y[..., None] * self.freqs[:, 1] + self.phases
        return self.amplitude * np.sin(arg).mean(axis=-1)


@dataclass
class _GroundCover:
    """Bumpy 0.2-0.7 m high shrub layer over a yard."""

    base: float
    height_fn: _Undulation

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        bumps = 0.15 * np.sin(1.7 * x + 0.3) * np.cos(1.3 * y + 0.7) + 3.0 * self.height_fn(x, y)
        return self.base + 0.45 + bumps


def block_sides(net: Network, i: int, j: int) -> list[tuple[object, int]]:
    """(street line, the line's side the block is on) for block sides 0..3."""
    return [(net.ys[j], 1), (net.xs[i + 1], 0), (net.ys[j + 1], 0), (net.xs[i], 1)]


def block_rects(net: Network, i: int, j: int):
    """Curb and inner rectangles of block (i, j) and per-side sidewalk widths."""
    x0 = net.xs[i].position + net.xs[i].curb(1)
    x1 = net.xs[i + 1].position - net.xs[i + 1].curb(0)
    y0 = net.ys[j].position + net.ys[j].curb(1)
    y1 = net.ys[j + 1].position - net.ys[j + 1].curb(0)
    sw = [line.sidewalk[side] for line, side in block_sides(net, i, j)]
    inner = (x0 + sw[3], y0 + sw[0], x1 - sw[1], y1 - sw[2])
    return (x0, y0, x1, y1), inner, sw


def _rounded_corners(curb, radius: float, inset: float = 0.0, n: int = 8) -> list[np.ndarray]:
    """Arc points of the 4 corners (BL, BR, TR, TL), counter-clockwise, of a rounded rectangle."""
    x0, y0, x1, y1 = curb
    x0, y0, x1, y1 = x0 + inset, y0 + inset, x1 - inset, y1 - inset
    r = max(radius - inset, 0.3)
    centers = [(x0 + r, y0 + r), (x1 - r, y0 + r), (x1 - r, y1 - r), (x0 + r, y1 - r)]
    starts = [np.pi, 1.5 * np.pi, 0.0, 0.5 * np.pi]
    arcs = []
    for (cx, cy), a0 in zip(centers, starts):
        angles = a0 + np.linspace(0.0, 0.5 * np.pi, n + 1)
        arcs.append(np.column_stack([cx + r * np.cos(angles), cy + r * np.sin(angles)]))
    return arcs


def included_blocks(net: Network, route_xy: np.ndarray, radius: float) -> list[tuple[int, int]]:
    """Blocks whose (warped) area comes within `radius` of the route (K, 2, world coordinates)."""
    tree = cKDTree(route_xy[:: max(1, len(route_xy) // 2000)])
    out = []
    for i in range(len(net.xs) - 1):
        for j in range(len(net.ys) - 1):
            x0, x1 = net.xs[i].position, net.xs[i + 1].position
            y0, y1 = net.ys[j].position, net.ys[j + 1].position
            outline = densify(np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]), 5.0, closed=True)
            if np.min(tree.query(net.warp.points(outline))[0]) < radius:
                out.append((i, j))
    return out


def build_world(rng: np.random.Generator, cfg: SimConfig, net: Network, route_xy: np.ndarray) -> World:
    """Build the static mesh around the ego route `route_xy` (K, 2, world coordinates); deterministic given rng."""
    ids = _Ids()
    height_fn = _terrain_height(rng)
    parts: list[TriangleMesh] = []
    blocks: list[Block] = []
    chosen = included_blocks(net, route_xy, cfg.view_radius)
    for i, j in chosen:
        mb = MeshBuilder(net.warp)
        blocks.append(_block(mb, rng, cfg, net, i, j, ids, height_fn))
        parts.append(mb.build())
    mb = MeshBuilder(net.warp)
    segments = _segments_of(chosen)
    for seg in segments:
        mb.axis = 0 if seg[0] == "h" else 1
        _segment_markings(mb, rng, cfg, net, seg)
    mb.axis = None
    corners = {(i + di, j + dj) for i, j in chosen for di in (0, 1) for dj in (0, 1)}
    for node in sorted(corners & set(net.roundabouts)):  # none in the default world
        _roundabout_island(mb, rng, net, node)
    xs = [b.curb[0] for b in blocks] + [b.curb[2] for b in blocks]
    ys = [b.curb[1] for b in blocks] + [b.curb[3] for b in blocks]
    _road_plane(mb, rng, (min(xs) - 40, min(ys) - 40, max(xs) + 40, max(ys) + 40))
    parts.append(mb.build())
    return World(concat_meshes(parts), net, blocks, ids.next)


def _roundabout_island(mb: MeshBuilder, rng, net: Network, node: tuple[int, int]) -> None:
    """Central island of a roundabout: a kerb ring (other-ground) round a lawn (terrain) with shrubs or a tree."""
    h, radius = net.curb_height, net.roundabouts[node]
    center = net.node(*node)
    angles = np.linspace(0.0, 2.0 * np.pi, max(12, int(2.0 * np.pi * radius / 1.0)), endpoint=False)
    ring = center + radius * np.column_stack([np.cos(angles), np.sin(angles)])
    kerb = wall_strip(ring, 0.0, h, closed=True)
    mb.add(kerb, "other-ground", "curb", sample_reflectivity(rng, "curb", len(kerb[1])))
    lawn = polygon_fan(np.concatenate([center[None], ring, ring[:1]]), h + 0.02)
    mb.add(lawn, "terrain", "grass", sample_reflectivity(rng, "grass", len(lawn[1])))
    if rng.random() < 0.5:
        objects.tree(mb, rng, center, h, rng.uniform(0.7, 1.0), clearance=2.5)
    for a in np.linspace(0.0, 2.0 * np.pi, 5, endpoint=False) + rng.uniform(0, 1):
        objects.bush(mb, rng, center + 0.55 * radius * np.array([np.cos(a), np.sin(a)]), h, rng.uniform(0.5, 0.9))


def _road_plane(mb: MeshBuilder, rng, bounds) -> None:
    x0, y0, x1, y1 = bounds
    v, t = grid_surface(x0, x1, y0, y1, 8.0)  # fine enough to follow the hills (sag <= 1.5 cm per cell)
    mb.add((v, t), "road", "asphalt", sample_reflectivity(rng, "asphalt", len(t)))


def _segments_of(blocks: list[tuple[int, int]]) -> list[tuple[str, int, int]]:
    """Street segments bordering the blocks: ('h', j, i) = horizontal line j between nodes i, i+1."""
    segs = set()
    for i, j in blocks:
        segs |= {("h", j, i), ("h", j + 1, i), ("v", i, j), ("v", i + 1, j)}
    return sorted(segs)


def _block(mb, rng, cfg: SimConfig, net: Network, i: int, j: int, ids: _Ids, height_fn) -> Block:
    """Curb, sidewalk ring, grass strips, street furniture, parking strips and lots of block (i, j)."""
    h = net.curb_height
    curb, inner, sw = block_rects(net, i, j)
    radius = net.corner_radius
    arcs = _rounded_corners(curb, radius)
    ix0, iy0, ix1, iy1 = inner
    q = [np.array(p) for p in ((ix0, iy0), (ix1, iy0), (ix1, iy1), (ix0, iy1))]
    outline, ring = [], []
    for k in range(4):  # corner arc fanned to the inner corner, then the side as a band to the next corner
        arc, nxt = arcs[k], arcs[(k + 1) % 4]
        ring.append(polygon_fan(np.concatenate([q[k][None], arc]), h))
        n = max(1, int(np.ceil(np.linalg.norm(nxt[0] - arc[-1]) / STEP)))
        t = np.linspace(0.0, 1.0, n + 1)[:, None]
        ring.append(strip(arc[-1] + t * (nxt[0] - arc[-1]), q[k] + t * (q[(k + 1) % 4] - q[k]), h))
        outline += [arc, arc[-1] + t[1:-1] * (nxt[0] - arc[-1])]
    mb.add(
        wall_strip(np.concatenate(outline), 0.0, h, closed=True), "sidewalk", "curb", sample_reflectivity(rng, "curb")
    )
    paving = merge(*ring)
    material = cfg.street.sidewalk_material
    mb.add(paving, "sidewalk", material, sample_reflectivity(rng, material, len(paving[1])))
    base = flat_grid(ix0, ix1, iy0, iy1, h - 0.01, 8.0)
    mb.add(base, "terrain", "grass", sample_reflectivity(rng, "grass", len(base[1])))
    for side, (line, line_side) in enumerate(block_sides(net, i, j)):
        mb.axis = side % 2
        _side_strip(mb, rng, cfg, net, curb, side, line, line_side, ids, height_fn)
    use = blocks.block_use(rng, cfg.lots)
    paths: list[np.ndarray] = []
    if use == "lots":
        _lots(mb, rng, cfg, inner, h, ids, height_fn)
    elif use == "park":
        paths = blocks.park(mb, rng, cfg, inner, h, height_fn)
    elif use == "plaza":
        paths = blocks.plaza(mb, rng, cfg, inner, h, ids)
    elif use == "parking":
        paths = blocks.parking_lot(mb, rng, cfg, inner, h, ids)
    mb.axis = None
    ins = [line.grass[s] + 0.6 * (line.sidewalk[s] - line.grass[s]) for line, s in block_sides(net, i, j)]
    walk_rect = (curb[0] + ins[3], curb[1] + ins[0], curb[2] - ins[1], curb[3] - ins[2])
    loop = np.concatenate(_rounded_corners(walk_rect, max(radius - float(np.mean(ins)), 0.5)))
    walks = [net.warp.points(densify(path, STEP, closed=True)) for path in paths]
    return Block((i, j), curb, inner, net.warp.points(densify(loop, STEP, closed=True)), walks)


@dataclass
class _Side:
    """One block side being furnished: t runs along it from the corner (t0..t1 clear of the corner arcs), offsets
    point away from the street; `occupied` holds the t of what already stands there."""

    mb: object
    rng: np.random.Generator
    cfg: SimConfig
    start: np.ndarray
    u: np.ndarray
    n: np.ndarray
    t0: float
    t1: float
    h: float
    ids: _Ids
    occupied: list[float] = field(default_factory=list)

    def at(self, t, offset) -> np.ndarray:
        return self.start + self.u * t + self.n * offset

    def free(self, t, gap=1.5) -> bool:
        return all(abs(t - o) > gap for o in self.occupied)

    def along(self) -> float:
        """The yaw along the side."""
        return float(np.arctan2(self.u[1], self.u[0]))


def _side_strip(mb, rng, cfg: SimConfig, net: Network, curb, side, line, line_side, ids, height_fn) -> None:
    """One block side: grass strip, trees, lights, signs, clutter; beyond the curb the parking strip."""
    x0, y0, x1, y1 = curb
    r, h = net.corner_radius, net.curb_height
    start = np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)][side], dtype=np.float64)
    length = (x1 - x0) if side % 2 == 0 else (y1 - y0)
    if length - 2 * r < 2.0:
        return
    s = _Side(mb, rng, cfg, start, _SIDE_U[side], _SIDE_N[side], r, length - r, h, ids)
    grass, sidewalk = line.grass[line_side], line.sidewalk[line_side]
    if grass > 0:
        _verge(s, grass, height_fn)
    _street_trees(s, grass, sidewalk)
    _street_lights(s)
    _end_signs(s)
    _street_objects(s, sidewalk)
    if cfg.objects.sidewalk_bicycle_prob > 0 and sidewalk > 2.4:  # no draw when off: the default world stays
        _sidewalk_bicycles(s)
    if rng.random() < 0.06 and sidewalk > 3.0:
        _bus_shelter(s, sidewalk)
    if cfg.street.signal_prob > 0 and line.main:  # traffic lights by the crossings (no draw when off)
        _signals(s)
    park = line.parking[line_side]
    if park > 0:
        if rng.random() < cfg.street.parking_label_prob:
            ts = np.linspace(s.t0, s.t1, max(2, int(np.ceil((s.t1 - s.t0) / STEP)) + 1))
            band = strip(np.array([s.at(t, 0.0) for t in ts]), np.array([s.at(t, -park) for t in ts]), PARK_Z)
            mb.add(band, "parking", "parking", sample_reflectivity(rng, "parking", len(band[1])))
        _parked_vehicles(mb, rng, cfg, s.at, s.u, s.t0, s.t1, park, ids)


def _verge(s: _Side, grass: float, height_fn) -> None:
    """The grass verge between curb and sidewalk, following half the terrain's undulation."""
    a, b = s.at(s.t0 + 0.5, 0.15), s.at(s.t1 - 0.5, grass)
    v, tr = grid_surface(
        min(a[0], b[0]), max(a[0], b[0]), min(a[1], b[1]), max(a[1], b[1]), 2.0,
        lambda x, y: s.h + 0.03 + 0.5 * height_fn(x, y),
    )  # fmt: skip
    s.mb.add((v, tr), "terrain", "grass", sample_reflectivity(s.rng, "grass", len(tr)))


def _street_trees(s: _Side, grass: float, sidewalk: float) -> None:
    """A row of street trees (on the verge, else in the sidewalk) at the config's spacing, with some probability."""
    obj, rng = s.cfg.objects, s.rng
    if rng.random() >= obj.street_tree_prob:
        return
    t = s.t0 + rng.uniform(2.0, 6.0)
    offset = grass / 2 if grass > 0 else min(obj.tree_offset, sidewalk - 0.6)
    scale = rng.uniform(0.8, 1.2)
    while t < s.t1 - 2.0:
        objects.tree(s.mb, rng, s.at(t, offset), s.h, scale * rng.uniform(0.85, 1.15), clearance=obj.tree_clearance)
        s.occupied.append(t)
        t += rng.uniform(*obj.tree_spacing)


def _street_lights(s: _Side) -> None:
    """Street lights by the curb at the pole spacing, where no tree stands."""
    t = s.t0 + s.rng.uniform(3.0, 15.0)
    while t < s.t1 - 3.0:
        if s.free(t):
            objects.street_light(s.mb, s.rng, s.at(t, 0.45), s.h, float(np.arctan2(-s.n[1], -s.n[0])))
            s.occupied.append(t)
        t += s.rng.uniform(*s.cfg.objects.pole_spacing)


def _end_signs(s: _Side) -> None:
    """A traffic sign near either end of the side, facing either way along it."""
    obj, rng = s.cfg.objects, s.rng
    for end in (s.t0 + rng.uniform(1.5, 6.0), s.t1 - rng.uniform(1.5, 6.0)):
        if rng.random() < obj.sign_prob / 2 and s.free(end, 1.0):
            face = s.along() + (np.pi if rng.random() < 0.5 else 0.0)
            objects.traffic_sign(s.mb, rng, s.at(end, 0.35), s.h, face, back="metal" if obj.sign_back_metal else None)
            s.occupied.append(end)


def _street_objects(s: _Side, sidewalk: float) -> None:
    """Clutter (bins, boxes) every ~20 m, at the curb or the lot side of the sidewalk."""
    rng = s.rng
    for t in np.arange(s.t0 + 5.0, s.t1 - 5.0, 20.0):
        tt = t + rng.uniform(-5, 5)
        if rng.random() < s.cfg.objects.object_prob and s.free(tt, 1.2):
            off = 0.5 if rng.random() < 0.5 else sidewalk - 0.5
            objects.other_object(s.mb, rng, s.at(tt, off), s.h, s.along())
            s.occupied.append(tt)


def _sidewalk_bicycles(s: _Side) -> None:
    """Groups of 1-4 bicycles standing across the sidewalk, 0.8 m apart, every ~20 m with some probability."""
    rng = s.rng
    for t in np.arange(s.t0 + 8.0, s.t1 - 8.0, 20.0):
        tt = t + rng.uniform(-5, 5)
        count = int(rng.integers(1, 5))
        if rng.random() < s.cfg.objects.sidewalk_bicycle_prob and s.free(tt, 1.0 + 0.8 * count):
            across = float(np.arctan2(s.n[1], s.n[0]))
            for k in range(count):
                c = s.at(tt + 0.8 * (k - (count - 1) / 2), 1.2)
                mesh = objects.two_wheeler(rng, "bicycle", s.ids.take())
                _add_mesh(s.mb, objects.place(mesh, across + rng.normal(0, 0.1), (c[0], c[1], s.h)))
            s.occupied.append(tt)


def _bus_shelter(s: _Side, sidewalk: float) -> None:
    """A bus shelter (other-structure) at the back of a wide sidewalk."""
    tt = s.rng.uniform(s.t0 + 5, max(s.t0 + 6, s.t1 - 8))
    c = s.at(tt, sidewalk - 0.8)
    shelter = merge(
        box([3.0, 1.2, 0.08], [0, 0, 2.4]),
        box([3.0, 0.05, 2.0], [0, 0.55, 1.2]),
        box([0.05, 1.1, 2.0], [-1.45, 0, 1.2]),
        box([0.05, 1.1, 2.0], [1.45, 0, 1.2]),
    )
    s.mb.add(transform(shelter, s.along(), (c[0], c[1], s.h)), "other-structure", "metal", 0.3)


def _signals(s: _Side) -> None:
    """Traffic lights at both crossings of a main street, facing the traffic that meets them."""
    for end, facing in ((s.t0 + 1.0, -1.0), (s.t1 - 1.0, 1.0)):
        if s.rng.random() < s.cfg.street.signal_prob and s.free(end, 1.0):
            face = s.along() + (np.pi if facing < 0 else 0.0)
            objects.traffic_light(s.mb, s.rng, s.at(end, 0.4), s.h, face)
            s.occupied.append(end)


def _parked_vehicles(mb, rng, cfg: SimConfig, at, u, t0, t1, park, ids: _Ids) -> None:
    """Fill a parking strip with cars, vans, trucks and motorcycles, nose against the traffic direction."""
    occupancy = rng.uniform(*cfg.objects.parked_occupancy)
    t = t0 + rng.uniform(0.5, 3.0)
    yaw = float(np.arctan2(-u[1], -u[0]))  # right-hand traffic circulates clockwise around a block
    while True:
        kind = rng.choice(4, p=np.asarray(cfg.objects.parked_weights) / np.sum(cfg.objects.parked_weights))
        length = (4.8, 8.5, 5.6, 2.2)[kind]
        if t + length > t1 - 0.5:
            break
        if rng.random() < occupancy:
            center = at(t + length / 2, -park / 2 - rng.uniform(-0.15, 0.15))
            inst = ids.take()
            if kind == 0:
                mesh = objects.car(rng, "car", inst, kind=str(rng.choice(["sedan", "hatch", "suv"], p=[0.5, 0.3, 0.2])))
            elif kind == 1:
                mesh = objects.truck(rng, "truck", inst)
            elif kind == 2:
                mesh = objects.van(rng, "other-vehicle", inst)
            else:
                mesh = objects.two_wheeler(rng, "motorcycle", inst, motor=True)
            flip = np.pi if rng.random() < 0.1 else 0.0
            _add_mesh(mb, objects.place(mesh, yaw + flip + rng.normal(0, 0.02), (center[0], center[1], 0.0)))
        t += length + rng.uniform(0.6, 2.5)


_add_mesh = add_mesh  # the name the tests and older code use


def _segment_markings(mb, rng, cfg: SimConfig, net: Network, seg) -> None:
    """Lane markings, crosswalks and traffic islands of one street segment."""
    kind, line_index, node = seg
    lines, cross = (net.ys, net.xs) if kind == "h" else (net.xs, net.ys)
    if not (0 <= line_index < len(lines) and 0 <= node < len(cross) - 1):
        return
    line = lines[line_index]
    a = cross[node].position + max(cross[node].curb(1), 0.0) + net.corner_radius
    b = cross[node + 1].position - cross[node + 1].curb(0) - net.corner_radius
    if b - a < 4.0:
        return
    c = line.position

    def rect(s0, s1, o0, o1, z=MARK_Z):  # in pieces of <= STEP along the street, so that they bend with it
        edges = np.linspace(s0, s1, max(1, int(np.ceil(abs(s1 - s0) / STEP))) + 1)
        pieces = []
        for a0, a1 in zip(edges[:-1], edges[1:]):
            pts = [(a0, o0), (a1, o0), (a1, o1), (a0, o1)]
            pieces.append(quad(*[(s, c + o, z) if kind == "h" else (c + o, s, z) for s, o in pts]))
        return merge(*pieces)

    stripes = []
    median = line.main and rng.random() < cfg.street.median_prob and b - a > 30.0
    if median:
        width = rng.uniform(1.2, min(2.4, 2 * line.lane_width - 3.0))
        m0, m1 = a + rng.uniform(3.0, 8.0), b - rng.uniform(3.0, 8.0)
        h = net.curb_height
        top = rect(m0, m1, -width / 2, width / 2, h)
        corners = [(m0, -width / 2), (m1, -width / 2), (m1, width / 2), (m0, width / 2)]
        ring = np.array([(s, c + o) if kind == "h" else (c + o, s) for s, o in corners])
        lawn = cfg.street.median_terrain_prob > 0 and rng.random() < cfg.street.median_terrain_prob
        if lawn:  # a lawn island with trees: kerb stones (other-ground) round a grass top (terrain)
            kerb = wall_strip(densify(ring, STEP, closed=True), 0.0, h, closed=True)
            mb.add(kerb, "other-ground", "curb", sample_reflectivity(rng, "curb", len(kerb[1])))
            mb.add(top, "terrain", "grass", sample_reflectivity(rng, "grass", len(top[1])))
            for s in np.arange(m0 + 5.0, m1 - 3.0, rng.uniform(8.0, 14.0)):
                xy = (s, c) if kind == "h" else (c, s)
                objects.tree(mb, rng, xy, h, rng.uniform(0.6, 0.8), clearance=4.0)  # lifted over the lanes
        else:
            island = merge(top, wall_strip(densify(ring, STEP, closed=True), 0.0, h, closed=True))
            mb.add(island, "other-ground", "curb", sample_reflectivity(rng, "curb", len(island[1])))
            for s in np.arange(m0 + 4.0, m1 - 2.0, rng.uniform(7.0, 12.0)):
                xy = (s, c) if kind == "h" else (c, s)
                objects.bush(mb, rng, xy, h, 0.6)
    if line.center_line and not median:
        if line.main:
            stripes += [rect(a, b, o - 0.06, o + 0.06) for o in (-0.12, 0.12)]
        else:
            stripes += [rect(s, min(s + 3.0, b), -0.06, 0.06) for s in np.arange(a + 1.0, b, 9.0)]
    if line.main:  # dashed lines between the lanes of each direction
        for k in range(1, line.lanes_per_direction):
            for o in (-k * line.lane_width, k * line.lane_width):
                stripes += [rect(s, min(s + 3.0, b), o - 0.06, o + 0.06) for s in np.arange(a + 2.0, b, 9.0)]
    for side, sign in ((0, -1.0), (1, 1.0)):
        if line.parking[side] > 0 or rng.random() < 0.5:
            edge = sign * (line.half_road - 0.1)
            stripes.append(rect(a, b, edge - 0.06, edge + 0.06))
    for end, direction in ((a, 1.0), (b, -1.0)):
        if rng.random() < cfg.street.crosswalk_prob:
            s0 = end + direction * 1.0
            s1 = s0 + direction * rng.uniform(3.0, 4.0)
            for o in np.arange(-line.half_road + 0.3, line.half_road - 0.5, 1.0):
                stripes.append(rect(min(s0, s1), max(s0, s1), o, o + 0.5))
    if stripes:
        paint = merge(*stripes)
        mb.add(paint, "lane-marking", "paint", sample_reflectivity(rng, "paint", len(paint[1])))


class _LotFrame:
    """Lot coordinates: u along the street frontage, v inward from the sidewalk edge."""

    def __init__(self, origin, u, n) -> None:
        self.origin, self.u, self.n = np.asarray(origin, float), np.asarray(u, float), np.asarray(n, float)

    def xy(self, uu, vv) -> np.ndarray:
        return self.origin + self.u * uu + self.n * vv

    def rect(self, u0, v0, u1, v1) -> tuple[float, float, float, float]:
        a, b = self.xy(u0, v0), self.xy(u1, v1)
        return min(a[0], b[0]), min(a[1], b[1]), max(a[0], b[0]), max(a[1], b[1])

    @property
    def yaw_out(self) -> float:
        return float(np.arctan2(-self.n[1], -self.n[0]))


def _lots(mb, rng, cfg: SimConfig, inner, h, ids: _Ids, height_fn) -> None:
    """Split the inner rectangle into frontage strips of lots (each side) and a back courtyard."""
    ix0, iy0, ix1, iy1 = inner
    if ix1 - ix0 < 4 or iy1 - iy0 < 4:
        return
    depth = min(rng.uniform(*cfg.lots.depth), (ix1 - ix0) / 2, (iy1 - iy0) / 2)
    urban = rng.random() < 0.35
    # (side, start corner, frontage length)
    strips = [
        (0, (ix0, iy0), ix1 - ix0),
        (2, (ix1, iy1), ix1 - ix0),
        (1, (ix1, iy0 + depth), iy1 - iy0 - 2 * depth),
        (3, (ix0, iy1 - depth), iy1 - iy0 - 2 * depth),
    ]
    for side, origin, length in strips:
        mb.axis = side % 2
        frame = _LotFrame(origin, _SIDE_U[side], _SIDE_N[side])
        u = 0.0
        while length - u > 3.0:
            width = rng.uniform(*cfg.lots.frontage)
            if length - u - width < cfg.lots.frontage[0] * 0.6:
                width = length - u
            _lot(mb, rng, cfg, frame, u, u + width, depth, h, ids, height_fn, urban, side)
            u += width
    mb.axis = None
    if ix1 - ix0 > 2 * depth + 2 and iy1 - iy0 > 2 * depth + 2:
        cx0, cy0, cx1, cy1 = ix0 + depth, iy0 + depth, ix1 - depth, iy1 - depth
        v, t = grid_surface(cx0, cx1, cy0, cy1, 6.0, lambda x, y: h + 0.05 + height_fn(x, y))
        mb.add((v, t), "terrain", "grass", sample_reflectivity(rng, "grass", len(t)))
        for _ in range(int((cx1 - cx0) * (cy1 - cy0) / cfg.lots.courtyard_tree_area)):
            objects.tree(mb, rng, (rng.uniform(cx0, cx1), rng.uniform(cy0, cy1)), h)


@dataclass
class _Lot:
    """One lot being built: where its meshes go, its draws, and its extent in lot coordinates (u0..u1 along the
    frontage, 0..depth inward) at ground height h."""

    mb: object
    rng: np.random.Generator
    cfg: SimConfig
    frame: _LotFrame
    u0: float
    u1: float
    depth: float
    h: float
    ids: _Ids
    height_fn: object
    side: int

    @property
    def width(self) -> float:
        return self.u1 - self.u0

    def yaw_in(self) -> float:
        """The yaw facing into the lot (its normal)."""
        return float(np.arctan2(self.frame.n[1], self.frame.n[0]))

    def ground(self, label, material, v0=0.0, v1=None, tessellate=False, ua=None, ub=None) -> None:
        """A ground patch of the lot (whole width and depth unless given), flat or following the terrain."""
        ua, ub, v1 = self.u0 if ua is None else ua, self.u1 if ub is None else ub, self.depth if v1 is None else v1
        x0, y0, x1, y1 = self.frame.rect(ua, v0, ub, v1)
        if tessellate:
            v, t = grid_surface(x0, x1, y0, y1, 2.0, lambda x, y: self.h + 0.05 + self.height_fn(x, y))
        else:
            v, t = flat_grid(x0, x1, y0, y1, self.h + 0.005)
        self.mb.add((v, t), label, material, sample_reflectivity(self.rng, material, len(t)))


def _lot(mb, rng, cfg: SimConfig, frame: _LotFrame, u0, u1, depth, h, ids, height_fn, urban, side) -> None:
    """One lot: ground, maybe a building, a front fence/hedge, yard vegetation, parked cars or bicycles."""
    lc = cfg.lots
    weights = np.asarray(lc.kind_weights, dtype=np.float64)
    if urban:
        weights = weights * [0.3, 3.0, 0.5, 1.0, 1.0]
    kind = ["house", "row", "garden", "parking", "commercial"][int(rng.choice(5, p=weights / weights.sum()))]
    lot = _Lot(mb, rng, cfg, frame, u0, u1, depth, h, ids, height_fn, side)
    if kind == "row":
        _row_lot(lot)
        return
    if kind == "parking":
        _parking_lot(lot)
        return
    drive = _driveway(rng, lc, kind, u0, u1, depth)  # (d0, d1, length) or None, no draw when off
    _yard_ground(lot, kind, drive)
    if kind == "garden":
        _garden_plants(lot)
        return
    commercial = kind == "commercial"
    setback, bdepth = _house(lot, commercial, drive)
    if commercial and rng.random() < 0.5:
        back = "metal" if cfg.objects.sign_back_metal else None
        objects.traffic_sign(mb, rng, frame.xy(u0 + 1.0, 0.5), h, frame.yaw_out, back=back)
    yard = max(setback - 1.0, 0.0)
    _yard_plants(lot, yard, setback + bdepth, drive)
    _front_fence(lot, drive)
    _shrub_bed(lot, yard, drive)
    _shed(lot, yard, drive)


def _row_lot(lot: _Lot) -> None:
    """A terraced row: sidewalk to the door, the building across the whole frontage, grass behind."""
    lc, rng = lot.cfg.lots, lot.rng
    setback = rng.uniform(*lc.row_setback)
    if setback > 0.2:
        lot.ground("sidewalk", lot.cfg.street.sidewalk_material, 0.0, setback)
    bdepth = min(rng.uniform(10.0, 16.0), lot.depth - setback - 0.5)
    lot.ground("terrain", "grass", setback + bdepth, lot.depth, tessellate=True)
    floors = int(rng.integers(lc.row_floors[0], lc.row_floors[1] + 1))
    fp = lot.frame.rect(lot.u0, setback, lot.u1, setback + bdepth)
    objects.building(lot.mb, rng, fp, floors, rng.uniform(*lc.floor_height), lot.side, lot.h - 0.2)


def _parking_lot(lot: _Lot) -> None:
    """A parking lot: one or two rows of cars, each space taken with a lot-wide probability."""
    rng = lot.rng
    lot.ground("parking", "parking")
    n_rows = int(rng.integers(1, 3))
    for row in range(n_rows):
        v = 3.0 + row * 11.0
        if v + 2.5 > lot.depth:
            break
        for uu in np.arange(lot.u0 + 1.5, lot.u1 - 1.5, rng.uniform(2.5, 3.0)):
            if rng.random() < rng.uniform(0.4, 0.9):
                c = lot.frame.xy(uu, v)
                inst = lot.ids.take()
                mesh = objects.car(rng, "car", inst, kind=str(rng.choice(["sedan", "hatch", "suv"])))
                yaw = lot.yaw_in() + (np.pi if rng.random() < 0.5 else 0)
                _add_mesh(lot.mb, objects.place(mesh, yaw, (c[0], c[1], lot.h)))


def _yard_ground(lot: _Lot, kind: str, drive) -> None:
    """The yard's ground (gravel, ground cover or grass around the driveway) and the paved driveway itself."""
    lc, rng, frame = lot.cfg.lots, lot.rng, lot.frame
    spans = _ground_spans(lot.u0, lot.u1, lot.depth, drive)
    gravel = rng.random() < lc.other_ground_prob
    if kind in ("house", "commercial", "garden"):
        if gravel:
            for ua, ub, v0, v1 in spans:
                lot.ground("other-ground", "gravel", v0, v1, ua=ua, ub=ub)
        elif rng.random() < lc.ground_cover_prob:  # low shrubs / ground cover over the yard (vegetation)
            for ua, ub, v0, v1 in spans:
                x0, y0, x1, y1 = frame.rect(ua, v0, ub, v1)
                v, t = grid_surface(x0, x1, y0, y1, 1.0, _GroundCover(lot.h, lot.height_fn))
                lot.mb.add((v, t), "vegetation", "hedge", sample_reflectivity(rng, "hedge", len(t)))
        else:
            for ua, ub, v0, v1 in spans:
                lot.ground("terrain", "grass", v0, v1, tessellate=True, ua=ua, ub=ub)
    if drive is not None:  # paved driveway from the sidewalk along the house (SemanticKITTI: parking)
        x0, y0, x1, y1 = frame.rect(drive[0], 0.0, drive[1], drive[2])
        v, t = flat_grid(x0, x1, y0, y1, lot.h + 0.01, 2.0)
        lot.mb.add((v, t), "parking", "parking", sample_reflectivity(rng, "parking", len(t)))


def _garden_plants(lot: _Lot) -> None:
    """A garden lot: trees and bushes by area, a front boundary leaning to hedges."""
    rng, frame, u0, u1, depth = lot.rng, lot.frame, lot.u0, lot.u1, lot.depth
    for _ in range(int(lot.width * depth / 40)):
        objects.tree(lot.mb, rng, frame.xy(rng.uniform(u0 + 1, u1 - 1), rng.uniform(2, depth - 1)), lot.h)
    for _ in range(int(lot.width * depth / 15)):
        objects.bush(lot.mb, rng, frame.xy(rng.uniform(u0 + 1, u1 - 1), rng.uniform(1, depth - 1)), lot.h)
    _front_boundary(lot.mb, rng, frame, u0, u1, lot.h, 1.0, lot.cfg.lots)


def _house(lot: _Lot, commercial: bool, drive) -> tuple[float, float]:
    """A house or shop set back from the sidewalk beside its driveway, with bicycles and cars by it; returns its
    (setback, building depth), drawn even when the lot is too small to build on."""
    lc, rng, frame, u0, u1 = lot.cfg.lots, lot.rng, lot.frame, lot.u0, lot.u1
    setback = rng.uniform(*lc.setback) * (1.5 if commercial else 1.0)
    gap = rng.uniform(1.0, 3.0) if not commercial else 0.5
    bdepth = min(rng.uniform(8.0, 14.0) * (1.4 if commercial else 1.0), lot.depth - setback - 1.0)
    lo, hi, room = u0 + gap, u1 - gap, lot.width - 2 * gap
    if drive is not None:  # the house stands beside its driveway
        if drive[0] - u0 < u1 - drive[1]:
            lo = max(lo, drive[1] + 0.5)
        else:
            hi = min(hi, drive[0] - 0.5)
        room = hi - lo
    if room <= 5.0 or bdepth <= 5.0:
        return setback, bdepth
    floors = 1 if commercial and rng.random() < 0.6 else int(rng.integers(lc.house_floors[0], lc.house_floors[1] + 1))
    fp = frame.rect(lo, setback, hi, setback + bdepth)
    storey = rng.uniform(*lc.floor_height) * (1.3 if commercial else 1.0)
    objects.building(lot.mb, rng, fp, floors, storey, lot.side, lot.h - 0.2)
    if rng.random() < lot.cfg.objects.bicycle_prob:
        for k in range(int(rng.integers(1, 4))):
            c = frame.xy(lo + 1.0 + 0.8 * k, setback - 0.6)
            mesh = objects.two_wheeler(rng, "bicycle", lot.ids.take())
            _add_mesh(lot.mb, objects.place(mesh, lot.yaw_in(), (c[0], c[1], lot.h)))
    if drive is None and not commercial and rng.random() < 0.3 and gap > 2.6 and setback > 5.5:
        c = frame.xy(u0 + gap / 2, setback)
        mesh = objects.car(rng, "car", lot.ids.take())
        _add_mesh(lot.mb, objects.place(mesh, lot.yaw_in(), (c[0], c[1], lot.h)))
    if drive is not None and rng.random() < 0.6 and drive[2] > 6.0:  # a car on the driveway
        c = frame.xy((drive[0] + drive[1]) / 2, rng.uniform(3.0, drive[2] - 2.5))
        yaw = lot.yaw_in() + (np.pi if rng.random() < 0.5 else 0.0)
        _add_mesh(lot.mb, objects.place(objects.car(rng, "car", lot.ids.take()), yaw, (c[0], c[1], lot.h)))
    return setback, bdepth


def _yard_plants(lot: _Lot, yard: float, behind: float, drive) -> None:
    """Trees in the front yard (or behind the building, at v = behind + 2, when the yard is shallow) and bushes."""
    lc, rng, frame, u0, u1 = lot.cfg.lots, lot.rng, lot.frame, lot.u0, lot.u1
    for _ in range(int(rng.integers(lc.yard_trees[0], lc.yard_trees[1] + 1))):
        if yard > 2.5:
            uu, vv, scale = rng.uniform(u0 + 1.5, u1 - 1.5), rng.uniform(1.5, yard), 0.8
        else:
            uu, vv, scale = rng.uniform(u0 + 1, u1 - 1), behind + 2.0, 1.0
        if not _on_drive(drive, uu, vv, 1.0):
            objects.tree(lot.mb, rng, frame.xy(uu, vv), lot.h, scale)
    for _ in range(int(rng.integers(lc.yard_bushes[0], lc.yard_bushes[1] + 1))):
        if yard > 1.2:
            uu, vv, size = rng.uniform(u0 + 0.8, u1 - 0.8), rng.uniform(0.8, yard), rng.uniform(0.8, 1.8)
            if not _on_drive(drive, uu, vv, 0.8):
                objects.bush(lot.mb, rng, frame.xy(uu, vv), lot.h, size)


def _front_fence(lot: _Lot, drive) -> None:
    """A fence or hedge along the sidewalk, open at the driveway."""
    lc, rng = lot.cfg.lots, lot.rng
    if rng.random() >= lc.front_fence_prob:
        return
    if drive is None:
        _front_boundary(lot.mb, rng, lot.frame, lot.u0, lot.u1, lot.h, 0.0, lc)
        return
    for a, b in ((lot.u0, drive[0]), (drive[1], lot.u1)):
        if b - a > 1.0:
            _front_boundary(lot.mb, rng, lot.frame, a, b, lot.h, 0.0, lc)


def _shrub_bed(lot: _Lot, yard: float, drive) -> None:
    """A planted bed of shrubs behind the fence line, in a yard deeper than 2 m."""
    rng = lot.rng
    if not (yard > 2.0 and rng.random() < lot.cfg.lots.shrub_bed_prob):
        return
    depth_bed = rng.uniform(1.2, min(3.0, yard))
    for uu in np.arange(lot.u0 + 0.8, lot.u1 - 0.8, rng.uniform(1.0, 1.6)):
        vv, size = rng.uniform(0.8, depth_bed), rng.uniform(0.6, 1.2)
        if not _on_drive(drive, uu, vv, 0.6):
            objects.bush(lot.mb, rng, lot.frame.xy(uu, vv), lot.h, size)


def _shed(lot: _Lot, yard: float, drive) -> None:
    """A garden shed in a deep, wide enough yard, unless it would stand on the driveway."""
    lc, rng, frame = lot.cfg.lots, lot.rng, lot.frame
    if not (lc.shed_prob > 0 and yard > 2.5 and lot.width > 5.0 and rng.random() < lc.shed_prob):
        return
    size = rng.uniform(1.2, [min(3.0, lot.width - 2.0), min(2.5, yard - 1.0)])
    uu = rng.uniform(lot.u0 + 0.6 + size[0] / 2, lot.u1 - 0.6 - size[0] / 2)
    if _on_drive(drive, uu, 1.0 + size[1] / 2, size[0] / 2 + 0.3):
        return
    yaw = float(np.arctan2(frame.u[1], frame.u[0]))
    objects.shed(lot.mb, rng, frame.xy(uu, 1.0 + size[1] / 2), lot.h, yaw, size)


def _driveway(rng, lc, kind: str, u0: float, u1: float, depth: float) -> tuple[float, float, float] | None:
    """(d0, d1, length) in lot coordinates of a house's driveway at one side of the lot, or None (no draw when off)."""
    if kind != "house" or lc.driveway_prob <= 0 or u1 - u0 < 10.0 or rng.random() >= lc.driveway_prob:
        return None
    width = rng.uniform(2.8, 3.6)
    d0 = u0 + 0.4 if rng.random() < 0.5 else u1 - 0.4 - width
    return d0, d0 + width, min(rng.uniform(8.0, 16.0), depth - 1.0)


def _ground_spans(u0: float, u1: float, depth: float, drive) -> list[tuple[float, float, float, float]]:
    """(u0, u1, v0, v1) pieces of a lot's ground: the whole lot, or all of it but the driveway."""
    if drive is None:
        return [(u0, u1, 0.0, depth)]
    d0, d1, length = drive
    spans = [(u0, d0, 0.0, depth), (d1, u1, 0.0, depth), (d0, d1, length, depth)]
    return [s for s in spans if s[1] - s[0] > 0.05 and s[3] - s[2] > 0.05]


def _on_drive(drive, u: float, v: float, margin: float) -> bool:
    """Whether lot point (u, v) lies within `margin` of the driveway (never without one)."""
    return drive is not None and drive[0] - margin < u < drive[1] + margin and v < drive[2] + margin


def _front_boundary(mb, rng, frame: _LotFrame, u0, u1, h, hedge_bias, lc) -> None:
    """Fence, wall or hedge along the lot front with an entrance gap."""
    gate = rng.uniform(u0 + 1.0, max(u0 + 1.5, u1 - 3.0))
    for a, b in ((u0 + 0.2, gate), (gate + 1.5, u1 - 0.2)):
        if b - a < 0.8:
            continue
        p0, p1 = frame.xy(a, 0.3), frame.xy(b, 0.3)
        if rng.random() < lc.hedge_prob + (1.0 - lc.hedge_prob) * hedge_bias:
            objects.hedge(mb, rng, p0, p1, h, lc.hedge_height)
        else:
            objects.fence(mb, rng, p0, p1, h)
