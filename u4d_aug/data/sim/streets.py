"""Street lattice of the simulated world and lane-following paths on it (right-hand traffic, as in KITTI).

Streets run along x ("horizontal" lines at y = Y[j]) and along y ("vertical" lines at x = X[i]) with random
spacings; every crossing is an intersection with rounded curbs. A route is a walk over intersections; its
path follows a lane at a fixed offset right of the street centre and turns on arcs concentric with the curb.

Streets bend: the world is laid out on the straight lattice ("lattice coordinates") and then mapped by a
smooth shear `Warp`, (x, y) -> (x + f_y(y), y + f_x(x)), so every x-street swings sideways by f_x (a sum of
two sines, curve radius >= `bend_min_radius`) and every y-street by f_y; intersections become slightly skewed.
Lanes, curbs, sidewalks, ground and buildings follow the map point by point (a shear: cross-sections narrow by
cos(heading), <= 6 % at the slope cap); compact objects (vehicles, trees, poles, signs) are moved rigidly and
turned to the local direction of their street, so they keep their shape.

The ground is not flat either: gentle hills `Hills` (a few plane waves, grade <= `hill_max_grade`, curvature
radius >= `hill_min_radius`) lift every surface point by point and set every compact object on the ground's
tangent plane at its anchor, so streets climb and yards fall away beside them (real seq 00: the ground 30 m to
the left of the sensor lies 0.7 m lower than under it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from u4d_aug.data.sim.config import StreetConfig

# headings: 0 +x, 1 +y, 2 -x, 3 -y  (counter-clockwise)
DIRECTIONS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])


@dataclass
class Line:
    """One street: centre-line coordinate and cross-section (index 0 = negative side, 1 = positive side)."""

    position: float
    lane_width: float
    lanes_per_direction: int
    parking: tuple[float, float]  # parking strip width per side (0 = none)
    sidewalk: tuple[float, float]
    grass: tuple[float, float]  # terrain strip between curb and sidewalk (0 = none)
    center_line: bool
    main: bool

    @property
    def half_road(self) -> float:
        return self.lane_width * self.lanes_per_direction

    def curb(self, side: int) -> float:
        """Distance from the centre line to the curb on `side`."""
        return self.half_road + self.parking[side]


@dataclass
class Bend:
    """Lateral offset of one street family, f(s) = sum_k a_k sin(w_k s + p_k) in metres, s along the street."""

    amplitude: np.ndarray  # (K,) m
    freq: np.ndarray  # (K,) rad/m
    phase: np.ndarray  # (K,) rad

    def __call__(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64)
        out = np.zeros_like(s)
        for a, w, p in zip(self.amplitude, self.freq, self.phase):
            out += a * np.sin(w * s + p)
        return out

    def slope(self, s: np.ndarray) -> np.ndarray:
        """df/ds."""
        s = np.asarray(s, dtype=np.float64)
        out = np.zeros_like(s)
        for a, w, p in zip(self.amplitude, self.freq, self.phase):
            out += a * w * np.cos(w * s + p)
        return out


@dataclass
class Hills:
    """Ground height h(p) = sum_k a_k sin(w_k . p + phase_k) in metres over world points p (gentle hills)."""

    amplitude: np.ndarray  # (K,) m
    wavevector: np.ndarray  # (K, 2) rad/m
    phase: np.ndarray  # (K,) rad

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """(...,) height at (..., 2) world points."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.sin(xy @ self.wavevector.T + self.phase) @ self.amplitude

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) grade dh/dxy at (..., 2) world points."""
        xy = np.asarray(xy, dtype=np.float64)
        return (np.cos(xy @ self.wavevector.T + self.phase) * self.amplitude) @ self.wavevector


def make_hills(rng: np.random.Generator, cfg: StreetConfig) -> Hills:
    """Three plane waves with random directions, wavelengths and phases, scaled to the grade/curvature caps."""
    flat = rng.random() < cfg.flat_prob
    amplitude = rng.uniform(*cfg.hill_amplitude, 3)
    angle = rng.uniform(0.0, 2.0 * np.pi, 3)
    freq = 2.0 * np.pi / rng.uniform(*cfg.hill_wavelength, 3)
    phase = rng.uniform(0.0, 2.0 * np.pi, 3)
    grade = float(np.sum(amplitude * freq))
    curvature = float(np.sum(amplitude * freq**2))
    scale = 0.0 if flat else min(1.0, cfg.hill_max_grade / grade, 1.0 / (cfg.hill_min_radius * curvature))
    return Hills(amplitude * scale, np.column_stack([np.cos(angle), np.sin(angle)]) * freq[:, None], phase)


@dataclass
class Warp:
    """Shear of the lattice plane that bends the streets: (x, y) -> (x + bend_y(y), y + bend_x(x)); with `hills`
    every point is also lifted by the ground height at its mapped position (compact objects: the tangent plane at
    their anchor)."""

    bend_x: Bend  # offset of x-streets (in y) as a function of x
    bend_y: Bend  # offset of y-streets (in x) as a function of y
    hills: Hills | None = None

    def points(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) lattice coordinates -> world coordinates."""
        xy = np.asarray(xy, dtype=np.float64)
        out = xy.copy()
        out[..., 0] += self.bend_y(xy[..., 1])
        out[..., 1] += self.bend_x(xy[..., 0])
        return out

    def turn(self, xy: np.ndarray, axis: int | None) -> np.ndarray:
        """Rotation (rad) that keeps an object aligned with its street: axis 0 x-street, 1 y-street, None mean."""
        xy = np.asarray(xy, dtype=np.float64)
        along_x = np.arctan(self.bend_x.slope(xy[..., 0]))  # direction of a mapped x-line
        along_y = -np.arctan(self.bend_y.slope(xy[..., 1]))  # a mapped y-line, measured from +y
        if axis == 0:
            return along_x
        if axis == 1:
            return along_y
        return 0.5 * (along_x + along_y)

    def place(self, vertices: np.ndarray, anchor: np.ndarray, axis: np.ndarray) -> np.ndarray:
        """Map (V, 3) vertices: where the (V, 2) anchor is NaN point by point, elsewhere rigidly, moved with the
        anchor and turned along the street of the (V,) axis (0 x-street, 1 y-street, -1 mean)."""
        out = np.array(vertices, dtype=np.float64)
        free = np.isnan(anchor[:, 0])
        out[free, :2] = self.points(out[free, :2])
        rigid = ~free
        a, ax = anchor[rigid], axis[rigid]
        angle = np.where(ax == 0, self.turn(a, 0), np.where(ax == 1, self.turn(a, 1), self.turn(a, None)))
        moved = self.points(a)
        c, s = np.cos(angle), np.sin(angle)
        dx, dy = out[rigid, 0] - a[:, 0], out[rigid, 1] - a[:, 1]
        out[rigid, 0] = moved[:, 0] + c * dx - s * dy
        out[rigid, 1] = moved[:, 1] + s * dx + c * dy
        if self.hills is not None:  # surfaces follow the ground point by point, objects its tangent plane
            out[free, 2] += self.hills(out[free, :2])
            grade = self.hills.gradient(moved)
            out[rigid, 2] += self.hills(moved) + np.einsum("ij,ij->i", grade, out[rigid, :2] - moved)
        return out


def _make_bend(rng: np.random.Generator, cfg: StreetConfig) -> Bend:
    """Two sines with random wavelengths and phases, scaled down to the slope and curve-radius limits."""
    straight = rng.random() < cfg.straight_prob
    amplitude = rng.uniform(*cfg.bend_amplitude, 2) * rng.choice([-1.0, 1.0], 2)
    freq = 2.0 * np.pi / rng.uniform(*cfg.bend_wavelength, 2)
    phase = rng.uniform(0.0, 2.0 * np.pi, 2)
    slope = float(np.sum(np.abs(amplitude) * freq))
    curvature = float(np.sum(np.abs(amplitude) * freq**2))
    scale = min(1.0, cfg.bend_max_slope / slope, 1.0 / (cfg.bend_min_radius * curvature))
    if straight:
        scale = 0.0
    return Bend(amplitude * scale, freq, phase)


@dataclass
class Network:
    """Street lattice: vertical lines (x = const, index i) and horizontal lines (y = const, index j), and the
    warp that bends it into the world."""

    xs: list[Line]
    ys: list[Line]
    corner_radius: float
    curb_height: float
    warp: Warp
    roundabouts: dict[tuple[int, int], float] = field(default_factory=dict)  # node -> central island radius, m

    def node(self, i: int, j: int) -> np.ndarray:
        return np.array([self.xs[i].position, self.ys[j].position])

    def line_of(self, i: int, j: int, heading: int) -> Line:
        """The street a heading travels on at node (i, j)."""
        return self.ys[j] if heading % 2 == 0 else self.xs[i]

    def inside(self, i: int, j: int) -> bool:
        return 0 <= i < len(self.xs) and 0 <= j < len(self.ys)


def _make_line(rng: np.random.Generator, cfg: StreetConfig, position: float) -> Line:
    main = bool(rng.random() < cfg.main_street_prob)
    lane_width = float(rng.uniform(*cfg.lane_width))
    parking = tuple(
        float(rng.uniform(*cfg.parking_width)) if rng.random() < cfg.parking_prob else 0.0 for _ in range(2)
    )
    sidewalk = tuple(float(rng.uniform(*cfg.sidewalk_width)) for _ in range(2))
    grass = tuple(
        float(min(rng.uniform(*cfg.grass_width), sw - 1.5)) if rng.random() < cfg.grass_strip_prob else 0.0
        for sw in sidewalk
    )
    center_line = main or bool(rng.random() < cfg.center_line_prob)
    lanes = 1
    if main:  # a draw only when the range allows a choice: the default (2, 2) keeps the default world's streams
        low, high = cfg.main_lanes
        lanes = low if low == high else int(rng.integers(low, high + 1))
    return Line(
        position=position,
        lane_width=lane_width,
        lanes_per_direction=lanes,
        parking=parking,  # type: ignore[arg-type]
        sidewalk=sidewalk,  # type: ignore[arg-type]
        grass=tuple(max(g, 0.0) for g in grass),  # type: ignore[arg-type]
        center_line=center_line,
        main=main,
    )


def _positions(rng: np.random.Generator, cfg: StreetConfig, extent: float) -> list[float]:
    """Street centre coordinates covering [-extent, extent], one line near 0."""
    first = float(rng.uniform(-10.0, 10.0))
    up, down = [first], [first]
    while up[-1] < extent:
        up.append(up[-1] + float(rng.uniform(*cfg.block_size)))
    while down[-1] > -extent:
        down.append(down[-1] - float(rng.uniform(*cfg.block_size)))
    return sorted(down[1:]) + up


def make_network(rng: np.random.Generator, cfg: StreetConfig, extent: float) -> Network:
    """Random street lattice covering a square of half-size `extent` metres around the origin, and its bends."""
    xs = [_make_line(rng, cfg, p) for p in _positions(rng, cfg, extent)]
    ys = [_make_line(rng, cfg, p) for p in _positions(rng, cfg, extent)]
    radius = float(rng.uniform(*cfg.corner_radius))
    min_sidewalk = min(min(line.sidewalk) for line in xs + ys)
    curb_height = float(rng.uniform(*cfg.curb_height))
    warp = Warp(_make_bend(rng, cfg), _make_bend(rng, cfg))
    net = Network(xs, ys, corner_radius=min(radius, 2.5 * min_sidewalk), curb_height=curb_height, warp=warp)
    if cfg.roundabout_prob > 0:  # drawn last, and only when asked: the default world keeps its streams
        for i in range(len(xs)):
            for j in range(len(ys)):
                if rng.random() < cfg.roundabout_prob and not (xs[i].main or ys[j].main):
                    island = min(float(rng.uniform(*cfg.roundabout_radius)), _island_room(net, i, j))
                    if island >= 2.0:
                        net.roundabouts[(i, j)] = island
    return net


RING_LANE = 2.5  # m from the island's kerb to the centre of the circulating lane
RING_CLEARANCE = 1.4  # m from the circulating lane centre to the corner kerbs (half a car and a margin)


def _island_room(net: Network, i: int, j: int) -> float:
    """Largest central island at node (i, j) whose circulating lane clears the four rounded corner kerbs."""
    r = net.corner_radius
    nearest = min(float(np.hypot(net.xs[i].curb(sx) + r, net.ys[j].curb(sy) + r)) - r for sx in (0, 1) for sy in (0, 1))
    return nearest - RING_CLEARANCE - RING_LANE


def ring_radius(net: Network, node: tuple[int, int], offset: float) -> float:
    """Radius of a roundabout path for a lane `offset` m right of its street's centre."""
    return max(net.roundabouts[node] + RING_LANE, abs(offset) + 1.0)


def plan_route(
    rng: np.random.Generator,
    net: Network,
    start: tuple[int, int],
    heading: int,
    length: float,
    turn_prob: float,
) -> list[tuple[int, int]]:
    """Walk over intersections from node `start` (entered with `heading`) until the walk covers `length` m;
    straight on with 1 - turn_prob, otherwise left or right, never a U-turn, never off the lattice."""
    nodes = [start]
    total = 0.0
    i, j = start
    while total < length:
        options = [heading, (heading + 1) % 4, (heading + 3) % 4]
        weights = np.array([1.0 - turn_prob, turn_prob / 2, turn_prob / 2])
        ok = []
        for h in options:
            di, dj = int(DIRECTIONS[h][0]), int(DIRECTIONS[h][1])
            ok.append(net.inside(i + di, j + dj) and net.inside(i + 2 * di, j + 2 * dj))
        ok = np.array(ok)
        if not ok.any():
            break
        weights = np.where(ok, weights, 0.0)
        heading = options[int(rng.choice(3, p=weights / weights.sum()))]
        di, dj = int(DIRECTIONS[heading][0]), int(DIRECTIONS[heading][1])
        total += float(np.linalg.norm(net.node(i + di, j + dj) - net.node(i, j)))
        i, j = i + di, j + dj
        nodes.append((i, j))
    return nodes


def _heading_between(a: tuple[int, int], b: tuple[int, int]) -> int:
    di, dj = b[0] - a[0], b[1] - a[1]
    return {(1, 0): 0, (0, 1): 1, (-1, 0): 2, (0, -1): 3}[(int(np.sign(di)), int(np.sign(dj)))]


def _right(heading: int) -> np.ndarray:
    return DIRECTIONS[(heading + 3) % 4]


def right_side(heading: int) -> int:
    """Side index (0 negative, 1 positive) of a street on the right of travel in direction `heading`."""
    # right of +x is -y and right of -y is -x: the negative side 0; right of +y / -x is the positive side 1
    return 0 if heading in (0, 3) else 1


def _curb_distance(line: Line, heading: int, offset: float, turn_right: bool) -> float:
    """Distance from a lane at `offset` right of centre to the curb on the turning side."""
    side = right_side(heading)
    if turn_right:
        return line.curb(side) - offset
    return line.curb(1 - side) + offset


def lane_path(
    net: Network, nodes: list[tuple[int, int]], offset_fn, spacing: float = 0.05, start_fraction: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Dense lane-following path over `nodes`: (K, 2) points `spacing` m apart and (K,) flags 1 on turn arcs.

    `offset_fn(line, side)` gives the lane centre's distance right of the street centre, side the index of the
    street side on the right of travel. The path starts
    `start_fraction` of the way along the first street segment and ends halfway along the last one.
    """
    pieces: list[np.ndarray] = []
    turning: list[np.ndarray] = []
    first_heading = _heading_between(nodes[0], nodes[1])
    line0 = net.line_of(*nodes[0], first_heading)
    a, b = net.node(*nodes[0]), net.node(*nodes[1])
    cursor = a + (b - a) * start_fraction + _right(first_heading) * offset_fn(line0, right_side(first_heading))
    for k in range(1, len(nodes) - 1):
        h1, h2 = _heading_between(nodes[k - 1], nodes[k]), _heading_between(nodes[k], nodes[k + 1])
        line1, line2 = net.line_of(*nodes[k], h1), net.line_of(*nodes[k], h2)
        o1, o2 = offset_fn(line1, right_side(h1)), offset_fn(line2, right_side(h2))
        node = net.node(*nodes[k])
        if nodes[k] in net.roundabouts:  # round the island counter-clockwise from the entry to the exit lane
            cursor = _roundabout(pieces, turning, cursor, node, h1, h2, o1, o2, ring_radius(net, nodes[k], max(o1, o2)))
            continue
        if h1 == h2:
            continue
        d1, d2 = DIRECTIONS[h1], DIRECTIONS[h2]
        # corner C where the incoming and outgoing lane centre lines cross
        p1, p2 = node + _right(h1) * o1, node + _right(h2) * o2
        corner = p1 + d1 * np.dot(p2 - p1, d1)
        turn_right = h2 == (h1 + 3) % 4
        radius = net.corner_radius + 0.5 * (
            _curb_distance(line1, h1, o1, turn_right) + _curb_distance(line2, h2, o2, turn_right)
        )
        t_in, t_out = corner - d1 * radius, corner + d2 * radius
        if not pieces and np.dot(t_in - cursor, d1) < spacing:  # the start lies inside the first turn
            cursor = t_in - d1 * spacing
        pieces.append(_segment(cursor, t_in, spacing))
        turning.append(np.zeros(len(pieces[-1])))
        normal = _right(h1) if turn_right else -_right(h1)
        center = t_in + normal * radius
        a0 = np.arctan2(*(t_in - center)[::-1])
        a1 = np.arctan2(*(t_out - center)[::-1])
        sweep = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
        n = max(2, int(abs(sweep) * radius / spacing))
        angles = a0 + sweep * np.arange(n) / n
        pieces.append(center + radius * np.column_stack([np.cos(angles), np.sin(angles)]))
        turning.append(np.ones(n))
        cursor = t_out
    h_last = _heading_between(nodes[-2], nodes[-1])
    line_last = net.line_of(*nodes[-1], h_last)
    end = (net.node(*nodes[-2]) + net.node(*nodes[-1])) / 2 + _right(h_last) * offset_fn(line_last, right_side(h_last))
    pieces.append(_segment(cursor, end, spacing, include_end=True))
    turning.append(np.zeros(len(pieces[-1])))
    return np.concatenate(pieces), np.concatenate(turning)


def _roundabout(pieces, turning, cursor, node, h1: int, h2: int, o1: float, o2: float, radius: float, spacing=0.05):
    """Append the approach to a roundabout and the arc round its centre `node`; returns the exit point."""
    d1, d2 = DIRECTIONS[h1], DIRECTIONS[h2]
    entry = node + _right(h1) * o1 - d1 * np.sqrt(radius**2 - o1**2)
    exit_ = node + _right(h2) * o2 + d2 * np.sqrt(radius**2 - o2**2)
    if not pieces and np.dot(entry - cursor, d1) < spacing:  # the start lies inside the roundabout
        cursor = entry - d1 * spacing
    pieces.append(_segment(cursor, entry, spacing))
    turning.append(np.zeros(len(pieces[-1])))
    a0 = np.arctan2(*(entry - node)[::-1])
    sweep = (np.arctan2(*(exit_ - node)[::-1]) - a0) % (2 * np.pi)  # counter-clockwise (right-hand traffic)
    n = max(2, int(sweep * radius / spacing))
    angles = a0 + sweep * np.arange(n) / n
    pieces.append(node + radius * np.column_stack([np.cos(angles), np.sin(angles)]))
    turning.append(np.ones(n))
    return exit_


def _segment(p0: np.ndarray, p1: np.ndarray, spacing: float, include_end: bool = False) -> np.ndarray:
    length = float(np.linalg.norm(p1 - p0))
    n = max(1, int(np.ceil(length / spacing)))
    t = np.arange(n + int(include_end)) / n
    return p0 + np.outer(t, p1 - p0)


def arc_length(path: np.ndarray) -> np.ndarray:
    """(K,) cumulative distance along a (K, 2) polyline."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])


def sample_path(path: np.ndarray, s: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) and headings (N,) rad at arc lengths `at` (clipped to the path)."""
    at = np.clip(at, 0.0, s[-1])
    x = np.interp(at, s, path[:, 0])
    y = np.interp(at, s, path[:, 1])
    ahead = np.clip(at + 0.5, 0.0, s[-1])
    behind = np.clip(at - 0.5, 0.0, s[-1])
    dx = np.interp(ahead, s, path[:, 0]) - np.interp(behind, s, path[:, 0])
    dy = np.interp(ahead, s, path[:, 1]) - np.interp(behind, s, path[:, 1])
    return np.column_stack([x, y]), np.arctan2(dy, dx)
