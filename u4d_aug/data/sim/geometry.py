"""Triangle-mesh building blocks of the simulated world: materials, a labelled mesh builder and primitives.

Every triangle carries a SemanticKITTI raw label, an instance id, a material and a reflectivity, so a ray
hit's primitive id is all the ray caster needs. Reflectivities follow the per-class mean remission measured on
the real SemanticKITTI seq-00 frames 0-2 at 5-20 m (../shared/data/real/SOURCES.md).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

# SemanticKITTI raw ids (semantic-kitti.yaml `labels:`), used by name so world code reads like the classes.
RAW = {
    "unlabeled": 0,
    "car": 10,
    "bicycle": 11,
    "motorcycle": 15,
    "truck": 18,
    "other-vehicle": 20,
    "person": 30,
    "bicyclist": 31,
    "motorcyclist": 32,
    "road": 40,
    "parking": 44,
    "sidewalk": 48,
    "other-ground": 49,
    "building": 50,
    "fence": 51,
    "other-structure": 52,
    "lane-marking": 60,
    "vegetation": 70,
    "trunk": 71,
    "terrain": 72,
    "pole": 80,
    "traffic-sign": 81,
    "other-object": 99,
    "moving-car": 252,
    "moving-bicyclist": 253,
    "moving-person": 254,
    "moving-motorcyclist": 255,
    "moving-truck": 258,
    "moving-other-vehicle": 259,
}
MOVING_RAW = (252, 253, 254, 255, 256, 257, 258, 259)


@dataclass(frozen=True)
class Material:
    """Surface: reflectivity mean/spread, chance a return reads 0, drop chance, canopy penetration."""

    name: str
    reflectivity: float
    spread: float  # std of the per-object reflectivity
    zero_prob: float = 0.0  # returns that read intensity 0 (dark paint, glass, wet asphalt)
    drop_prob: float = 0.0  # rays lost (glass, spokes)
    penetration: float = 0.0  # m, mean extra range into porous surfaces (leaves)


# Means: real remission per class at 5-20 m (road 0.22, sidewalk/parking 0.31, building 0.44, vegetation 0.36,
# terrain 0.38, trunk 0.38, car 0.12 with 50 % zeros, pole 0.2 with 30 % zeros, lane marking 0.45), raised
# where the intensity model's incidence term lowers them (facades, leaves, grass; checked with sim-report).
MATERIALS = (
    Material("asphalt", 0.24, 0.03, zero_prob=0.08),
    Material("parking", 0.31, 0.04, zero_prob=0.01),
    Material("paint", 0.50, 0.08),
    Material("paving", 0.34, 0.04, zero_prob=0.01),
    Material("curb", 0.34, 0.04),
    Material("facade", 0.54, 0.12, zero_prob=0.01),
    Material("glass", 0.06, 0.04, zero_prob=0.7, drop_prob=0.5),
    Material("roof", 0.30, 0.08),
    Material("leaves", 0.42, 0.06, zero_prob=0.01, penetration=0.25),
    Material("hedge", 0.40, 0.05, penetration=0.12),
    Material("bark", 0.39, 0.05),
    Material("grass", 0.42, 0.05),
    Material("gravel", 0.30, 0.05),
    Material("car_paint", 0.26, 0.10, zero_prob=0.3),
    Material("car_glass", 0.03, 0.03, zero_prob=0.85, drop_prob=0.35),
    Material("tire", 0.06, 0.04, zero_prob=0.5),
    Material("metal", 0.26, 0.08, zero_prob=0.2),
    Material("sign", 0.62, 0.12),
    Material("fence", 0.30, 0.08),
    Material("clothes", 0.22, 0.08, zero_prob=0.2),
    Material("skin", 0.30, 0.05),
    Material("plastic", 0.30, 0.10, zero_prob=0.1),
    Material("spokes", 0.20, 0.05, zero_prob=0.3, drop_prob=0.7),
    # street types (scenes.py); appended so the indices above (and the default world) stay as they were
    Material("concrete", 0.36, 0.05, zero_prob=0.01),  # arterial sidewalks: plain slabs, a little brighter
    Material("cobble", 0.28, 0.06, zero_prob=0.02),  # squares: setts with dark joints
)
MAT = {m.name: i for i, m in enumerate(MATERIALS)}


@dataclass
class TriangleMesh:
    """Labelled triangle soup: per-triangle raw label, instance id, material index and reflectivity."""

    vertices: np.ndarray  # (V, 3) float32, metres
    triangles: np.ndarray  # (T, 3) uint32 vertex indices
    semantic: np.ndarray  # (T,) uint16 SemanticKITTI raw id
    instance: np.ndarray  # (T,) uint16, 0 for stuff
    material: np.ndarray  # (T,) uint8 index into MATERIALS
    reflectivity: np.ndarray  # (T,) float32 in [0, 1]

    @property
    def num_triangles(self) -> int:
        return len(self.triangles)


# labels of compact objects that a bending street carries rigidly (see streets.Warp), when under RIGID_EXTENT
RIGID_LABELS = frozenset(
    RAW[name]
    for name in (
        "car",
        "bicycle",
        "motorcycle",
        "truck",
        "other-vehicle",
        "person",
        "bicyclist",
        "motorcyclist",
        "other-structure",
        "vegetation",
        "trunk",
        "pole",
        "traffic-sign",
        "other-object",
    )
)
RIGID_EXTENT = 12.0  # m, larger parts (ground cover, long walls) follow the warp point by point


class MeshBuilder:
    """Collects labelled parts and concatenates them once (`build`).

    With a `warp` (streets.Warp) `build` maps every part: surfaces point by point, compact objects (RIGID_LABELS,
    or everything added inside `with builder.rigid(anchor)`) rigidly, turned along the street `axis` they were
    added under.
    """

    def __init__(self, warp=None) -> None:
        self._vertices: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._per_triangle: list[tuple[int, int, int, np.ndarray]] = []
        self._count = 0
        self.warp = warp
        self.axis: int | None = None  # street the parts being added belong to: 0 x-street, 1 y-street
        self._anchor: np.ndarray | None = None
        self._placement: list[tuple[np.ndarray, int]] = []  # per part: rigid anchor (NaN: none), street axis

    @contextmanager
    def rigid(self, anchor):
        """Parts added inside move rigidly with the (x, y) anchor (buildings, whole vehicles, trees)."""
        outer = self._anchor
        if outer is None:
            self._anchor = np.asarray(anchor, dtype=np.float64)[:2]
        try:
            yield self
        finally:
            self._anchor = outer

    def _anchor_of(self, vertices: np.ndarray, raw: int) -> np.ndarray:
        """(2,) point the part moves rigidly with, NaN when it follows the warp point by point."""
        if self._anchor is not None:
            return self._anchor
        if raw in RIGID_LABELS:
            low, high = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
            if np.all(high - low <= RIGID_EXTENT):
                return (low + high) / 2
        return np.full(2, np.nan)

    def add(
        self,
        part: tuple[np.ndarray, np.ndarray],
        label: str | int,
        material: str,
        reflectivity: float | np.ndarray,
        instance: int = 0,
    ) -> None:
        """Add (vertices (V,3), triangles (T,3)) with one label/material and a scalar or (T,) reflectivity."""
        vertices, triangles = part
        if len(triangles) == 0:
            return
        raw = RAW[label] if isinstance(label, str) else int(label)
        refl = np.broadcast_to(np.asarray(reflectivity, dtype=np.float32), (len(triangles),))
        vertices = np.asarray(vertices, dtype=np.float64)
        self._vertices.append(vertices)
        if self.warp is not None:
            self._placement.append((self._anchor_of(vertices, raw), -1 if self.axis is None else self.axis))
        self._triangles.append(np.asarray(triangles, dtype=np.int64) + self._count)
        self._per_triangle.append((raw, instance, MAT[material], refl))
        self._count += len(vertices)

    def build(self) -> TriangleMesh:
        """Concatenate all parts into one TriangleMesh."""
        if not self._triangles:
            return empty_mesh()
        sizes = [len(t) for t in self._triangles]
        vertices = np.concatenate(self._vertices)
        if self.warp is not None:  # all parts at once: much faster than part by part
            counts = [len(v) for v in self._vertices]
            anchor = np.repeat(np.stack([p[0] for p in self._placement]), counts, axis=0)
            axis = np.repeat(np.array([p[1] for p in self._placement], dtype=np.int8), counts)
            vertices = self.warp.place(vertices, anchor, axis)
        return TriangleMesh(
            vertices=vertices.astype(np.float32),
            triangles=np.concatenate(self._triangles).astype(np.uint32),
            semantic=np.repeat([p[0] for p in self._per_triangle], sizes).astype(np.uint16),
            instance=np.repeat([p[1] for p in self._per_triangle], sizes).astype(np.uint16),
            material=np.repeat([p[2] for p in self._per_triangle], sizes).astype(np.uint8),
            reflectivity=np.concatenate([p[3] for p in self._per_triangle]).astype(np.float32),
        )


def add_mesh(mb: MeshBuilder, mesh: TriangleMesh) -> None:
    """Add a ready TriangleMesh (one object, moved rigidly by a warp) part by part, keeping its attributes."""
    low, high = mesh.vertices[:, :2].min(axis=0), mesh.vertices[:, :2].max(axis=0)
    with mb.rigid((low + high) / 2):
        for key in np.unique(np.stack([mesh.semantic, mesh.instance, mesh.material]), axis=1).T:
            sel = (mesh.semantic == key[0]) & (mesh.instance == key[1]) & (mesh.material == key[2])
            used, inverse = np.unique(mesh.triangles[sel], return_inverse=True)
            mb.add(
                (mesh.vertices[used], inverse.reshape(-1, 3)),
                int(key[0]),
                MATERIALS[int(key[2])].name,
                mesh.reflectivity[sel],
                int(key[1]),
            )


def empty_mesh() -> TriangleMesh:
    """A mesh with no triangles."""
    return TriangleMesh(
        np.zeros((0, 3), np.float32),
        np.zeros((0, 3), np.uint32),
        np.zeros(0, np.uint16),
        np.zeros(0, np.uint16),
        np.zeros(0, np.uint8),
        np.zeros(0, np.float32),
    )


def concat_meshes(meshes: list[TriangleMesh]) -> TriangleMesh:
    """Concatenate meshes (vertex indices shifted)."""
    meshes = [m for m in meshes if m.num_triangles]
    if not meshes:
        return empty_mesh()
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return TriangleMesh(
        vertices=np.concatenate([m.vertices for m in meshes]),
        triangles=np.concatenate([m.triangles + np.uint32(o) for m, o in zip(meshes, offsets)]),
        semantic=np.concatenate([m.semantic for m in meshes]),
        instance=np.concatenate([m.instance for m in meshes]),
        material=np.concatenate([m.material for m in meshes]),
        reflectivity=np.concatenate([m.reflectivity for m in meshes]),
    )


def sample_reflectivity(rng: np.random.Generator, material: str, num_triangles: int = 1) -> np.ndarray:
    """Per-object reflectivity N(mean, spread) with a 6 % per-triangle variation, clipped to [0.01, 1]."""
    m = MATERIALS[MAT[material]]
    base = m.reflectivity + m.spread * rng.standard_normal()
    return np.clip(base * (1.0 + 0.06 * rng.standard_normal(num_triangles)), 0.01, 1.0).astype(np.float32)


# ------------------------------------------------------------------------------------------------------------
# primitives: each returns (vertices (V, 3) float64, triangles (T, 3) int64), outward-facing where it matters


def transform(part: tuple[np.ndarray, np.ndarray], yaw: float = 0.0, translation=(0.0, 0.0, 0.0)):
    """Rotate about z by yaw (rad), then translate."""
    vertices, triangles = part
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return vertices @ rot.T + np.asarray(translation, dtype=np.float64), triangles


def merge(*parts: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate parts that share one label/material."""
    vertices, triangles, count = [], [], 0
    for v, t in parts:
        vertices.append(v)
        triangles.append(t + count)
        count += len(v)
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(vertices), np.concatenate(triangles)


_BOX_TRIANGLES = np.array(
    [
        [0, 2, 1],
        [0, 3, 2],
        [4, 5, 6],
        [4, 6, 7],
        [0, 1, 5],
        [0, 5, 4],
        [1, 2, 6],
        [1, 6, 5],
        [2, 3, 7],
        [2, 7, 6],
        [3, 0, 4],
        [3, 4, 7],
    ]
)


def box(size, center=(0.0, 0.0, 0.0), bottom: bool = True):
    """Axis-aligned box with the given (sx, sy, sz) centred at `center`."""
    sx, sy, sz = np.asarray(size, dtype=np.float64) / 2.0
    corners = np.array([[-sx, -sy, -sz], [sx, -sy, -sz], [sx, sy, -sz], [-sx, sy, -sz]])
    vertices = np.concatenate([corners, corners * [1, 1, -1]]) + np.asarray(center, dtype=np.float64)
    triangles = _BOX_TRIANGLES if bottom else _BOX_TRIANGLES[2:]
    return vertices, triangles.copy()


def quad(p0, p1, p2, p3):
    """Planar quad p0-p1-p2-p3 (counter-clockwise seen from the front) as two triangles."""
    return np.array([p0, p1, p2, p3], dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def densify(points_xy: np.ndarray, step: float, closed: bool = False) -> np.ndarray:
    """Polyline with extra points so that no edge is longer than `step` (keeps the original points)."""
    pts = np.asarray(points_xy, dtype=np.float64)
    ends = np.concatenate([pts[1:], pts[:1]]) if closed else pts[1:]
    out = []
    for a, b in zip(pts, ends):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + np.outer(np.arange(n) / n, b - a))
    if not closed:
        out.append(pts[-1:])
    return np.concatenate(out)


def strip(outer: np.ndarray, inner: np.ndarray, z: float):
    """Horizontal band at height z between two matching (K, 2) polylines (quad per consecutive pair)."""
    k = len(outer)
    vertices = np.concatenate([np.column_stack([outer, np.full(k, z)]), np.column_stack([inner, np.full(k, z)])])
    i = np.arange(k - 1)
    triangles = np.concatenate([np.column_stack([i, i + 1, i + k + 1]), np.column_stack([i, i + k + 1, i + k])])
    return vertices, triangles


def flat_grid(x0: float, x1: float, y0: float, y1: float, z: float, cell: float = 4.0):
    """Horizontal rectangle at height z in ~cell-sized quads (so a warp can bend its edges)."""
    return grid_surface(x0, x1, y0, y1, cell, _Level(z))


@dataclass
class _Level:
    z: float

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.full_like(x, self.z)


def polygon_fan(points_xy: np.ndarray, z: float):
    """Horizontal convex polygon at height z (fan from the first vertex)."""
    n = len(points_xy)
    vertices = np.column_stack([points_xy, np.full(n, z)])
    triangles = np.column_stack([np.zeros(n - 2, np.int64), np.arange(1, n - 1), np.arange(2, n)])
    return vertices, triangles


def wall_strip(points_xy: np.ndarray, z0, z1, closed: bool = False):
    """Vertical band along a polyline from z0 to z1 (scalars or per-point arrays)."""
    pts = np.asarray(points_xy, dtype=np.float64)
    if closed:
        pts = np.concatenate([pts, pts[:1]])
    n = len(pts)
    z0 = np.broadcast_to(np.asarray(z0, dtype=np.float64), (n,))
    z1 = np.broadcast_to(np.asarray(z1, dtype=np.float64), (n,))
    vertices = np.concatenate([np.column_stack([pts, z0]), np.column_stack([pts, z1])])
    i = np.arange(n - 1)
    triangles = np.concatenate([np.column_stack([i, i + 1, i + n + 1]), np.column_stack([i, i + n + 1, i + n])])
    return vertices, triangles


def extrude_profile(profile_xz: np.ndarray, width: float):
    """Convex side profile (K, 2) in the x-z plane extruded symmetrically along y (car bodies, roofs)."""
    k = len(profile_xz)
    half = width / 2.0
    left = np.column_stack([profile_xz[:, 0], np.full(k, half), profile_xz[:, 1]])
    right = left * [1, -1, 1]
    vertices = np.concatenate([left, right])
    i = np.arange(k)
    j = (i + 1) % k
    sides = np.concatenate([np.column_stack([i, j, j + k]), np.column_stack([i, j + k, i + k])])
    caps = np.concatenate(
        [
            np.column_stack([np.zeros(k - 2, np.int64), np.arange(1, k - 1), np.arange(2, k)]),
            np.column_stack([np.full(k - 2, k), np.arange(k + 2, 2 * k), np.arange(k + 1, 2 * k - 1)]),
        ]
    )
    return vertices, np.concatenate([sides, caps])


def cylinder(radius: float, z0: float, z1: float, segments: int = 8, cap: bool = True, center=(0.0, 0.0)):
    """Vertical cylinder (poles, trunks) from z0 to z1."""
    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring = np.column_stack([np.cos(angles), np.sin(angles)]) * radius + np.asarray(center, dtype=np.float64)
    vertices, triangles = wall_strip(ring, z0, z1, closed=True)
    if cap:
        top = polygon_fan(ring, z1)
        vertices, triangles = merge((vertices, triangles), top)
    return vertices, triangles


def disc_y(radius: float, thickness: float, segments: int = 10):
    """Wheel: a short cylinder whose axis is y, centred at the origin."""
    v, t = cylinder(radius, -thickness / 2, thickness / 2, segments)
    bottom = polygon_fan(v[:segments, :2], -thickness / 2)
    v, t = merge((v, t), bottom)
    return v[:, [0, 2, 1]], t


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    phi = (1.0 + 5.0**0.5) / 2.0
    v = np.array(
        [
            [-1, phi, 0],
            [1, phi, 0],
            [-1, -phi, 0],
            [1, -phi, 0],
            [0, -1, phi],
            [0, 1, phi],
            [0, -1, -phi],
            [0, 1, -phi],
            [phi, 0, -1],
            [phi, 0, 1],
            [-phi, 0, -1],
            [-phi, 0, 1],
        ],
        dtype=np.float64,
    )
    f = np.array(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ]
    )
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = v[unique].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inverse.reshape(3, -1) + len(v)  # midpoints of edges 01, 12, 20 for every face
        v = np.concatenate([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        f = np.concatenate(
            [
                np.column_stack([a, m[0], m[2]]),
                np.column_stack([b, m[1], m[0]]),
                np.column_stack([c, m[2], m[1]]),
                np.column_stack([m[0], m[1], m[2]]),
            ]
        )
    return v, f


_ICOSPHERES = {n: _icosphere(n) for n in (0, 1, 2)}


def blob(rng: np.random.Generator, radii, center, subdivisions: int = 2, roughness: float = 0.25):
    """Irregular ellipsoid (tree canopy, bush): unit icosphere with low-frequency radial noise."""
    unit, triangles = _ICOSPHERES[subdivisions]
    freqs = rng.normal(0.0, 2.5, (5, 3))
    phases = rng.uniform(0.0, 2.0 * np.pi, 5)
    noise = np.sin(unit @ freqs.T + phases).sum(axis=1) / np.sqrt(5.0)
    scale = 1.0 + roughness * noise
    vertices = unit * scale[:, None] * np.asarray(radii, dtype=np.float64) + np.asarray(center, dtype=np.float64)
    return vertices, triangles.copy()


def grid_surface(x0: float, x1: float, y0: float, y1: float, cell: float, height_fn=None):
    """Horizontal rectangle tessellated into ~cell-sized quads; z from height_fn(x, y) (default 0)."""
    nx = max(1, int(np.ceil((x1 - x0) / cell)))
    ny = max(1, int(np.ceil((y1 - y0) / cell)))
    xs, ys = np.meshgrid(np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1), indexing="ij")
    z = np.zeros_like(xs) if height_fn is None else height_fn(xs, ys)
    vertices = np.column_stack([xs.ravel(), ys.ravel(), z.ravel()])
    idx = np.arange((nx + 1) * (ny + 1)).reshape(nx + 1, ny + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    triangles = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return vertices, triangles
