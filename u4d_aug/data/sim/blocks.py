"""Whole blocks of another use than building lots: parks, paved squares and parking lots (street types, scenes.py).

A block's inner rectangle (behind its sidewalk ring, lattice coordinates) is filled by one of these instead of lots
when `lots.park_block_prob` / `plaza_block_prob` / `parking_block_prob` say so (all 0 in the default world, which
then draws nothing here). Classes follow SemanticKITTI's definitions: lawns are terrain, paved footpaths and squares
sidewalk, gravel paths other-ground, parking lots parking (their painted stall lines too), benches and bins
other-object, kiosks building, lamp posts pole. Each returns closed walks (lattice coordinates) for pedestrians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from u4d_aug.data.sim import objects
from u4d_aug.data.sim.config import LotConfig, SimConfig
from u4d_aug.data.sim.geometry import (
    MeshBuilder,
    add_mesh,
    box,
    cylinder,
    flat_grid,
    grid_surface,
    merge,
    polygon_fan,
    quad,
    sample_reflectivity,
)

BLOCK_USES = ("lots", "park", "plaza", "parking")


def block_use(rng: np.random.Generator, lots: LotConfig) -> str:
    """What fills a block: lots, or a park / plaza / parking lot by their probabilities (no draw when all are 0)."""
    probs = (lots.park_block_prob, lots.plaza_block_prob, lots.parking_block_prob)
    if sum(probs) <= 0:
        return "lots"
    u = rng.random()
    for name, p in zip(BLOCK_USES[1:], probs):
        if u < p:
            return name
        u -= p
    return "lots"


@dataclass
class _Raised:
    """Height function lifted by `base` metres (lawns and paths following the ground undulation)."""

    height_fn: object
    base: float

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.base + self.height_fn(x, y)


def _loop(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """(4, 2) corners of an axis-aligned rectangle, counter-clockwise (a closed walk)."""
    return np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], dtype=np.float64)


def park(mb: MeshBuilder, rng: np.random.Generator, cfg: SimConfig, inner, h: float, height_fn) -> list[np.ndarray]:
    """Park: undulating lawn, a cross of footpaths (paved or gravel), scattered trees and shrubs, lamps, benches."""
    x0, y0, x1, y1 = inner
    if x1 - x0 < 12.0 or y1 - y0 < 12.0:
        return []
    lawn = grid_surface(x0, x1, y0, y1, 2.0, _Raised(height_fn, h + 0.05))
    mb.add(lawn, "terrain", "grass", sample_reflectivity(rng, "grass", len(lawn[1])))
    width = rng.uniform(2.0, 3.0)
    px = rng.uniform(x0 + 0.3 * (x1 - x0), x0 + 0.7 * (x1 - x0))
    py = rng.uniform(y0 + 0.3 * (y1 - y0), y0 + 0.7 * (y1 - y0))
    if rng.random() < 0.4:
        label, material = "other-ground", "gravel"
    else:
        label, material = "sidewalk", cfg.street.sidewalk_material
    raised = _Raised(height_fn, h + 0.09)
    for rect in ((x0, py - width / 2, x1, py + width / 2), (px - width / 2, y0, px + width / 2, y1)):
        path = grid_surface(rect[0], rect[2], rect[1], rect[3], 2.0, raised)
        mb.add(path, label, material, sample_reflectivity(rng, material, len(path[1])))
    clear = width / 2 + 1.5
    area = (x1 - x0) * (y1 - y0)
    for _ in range(int(area / rng.uniform(40.0, 90.0))):
        x, y = rng.uniform(x0 + 1.5, x1 - 1.5), rng.uniform(y0 + 1.5, y1 - 1.5)
        if abs(x - px) > clear and abs(y - py) > clear:
            objects.tree(mb, rng, (x, y), h + 0.05, rng.uniform(0.7, 1.2), clearance=2.0)
    for _ in range(int(area / 90.0)):
        x, y = rng.uniform(x0 + 1.0, x1 - 1.0), rng.uniform(y0 + 1.0, y1 - 1.0)
        if abs(x - px) > clear and abs(y - py) > clear:
            objects.bush(mb, rng, (x, y), h + 0.05, rng.uniform(0.7, 1.6))
    for along_x in (True, False):  # lamps and benches beside the paths
        start, end = (x0, x1) if along_x else (y0, y1)
        for t in np.arange(start + rng.uniform(4.0, 10.0), end - 3.0, rng.uniform(18.0, 26.0)):
            xy = (t, py + width / 2 + 0.4) if along_x else (px + width / 2 + 0.4, t)
            objects.street_light(mb, rng, xy, h + 0.09, 0.0 if along_x else np.pi / 2)
            if rng.random() < 0.6:
                bench = (t + 3.0, py - width / 2 - 0.5) if along_x else (px - width / 2 - 0.5, t + 3.0)
                objects.other_object(mb, rng, bench, h + 0.09, 0.0 if along_x else np.pi / 2)
    edge = rng.random()  # a shrub belt or a low fence round the lawn, open where the paths leave the park
    if edge < 0.85:
        _perimeter(mb, rng, inner, (px, py, px, py), width / 2 + 0.5, h, "hedge" if edge < 0.7 else "fence")
    return [np.array([(x0, py), (x1, py)]), np.array([(px, y0), (px, y1)])]


def _perimeter(mb: MeshBuilder, rng: np.random.Generator, rect, cuts, half_gap: float, h: float, kind: str) -> None:
    """Hedge or fence 0.6 m inside the rectangle's four sides (bottom, right, top, left), each open `half_gap` m
    either side of its cut (x for bottom/top, y for right/left)."""
    x0, y0, x1, y1 = rect
    corners = [np.array(c, dtype=np.float64) for c in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
    for side in range(4):
        a, b = corners[side], corners[(side + 1) % 4]
        along = b - a
        length = float(np.linalg.norm(along))
        inward = np.array([-along[1], along[0]]) / length
        axis = 0 if side % 2 == 0 else 1
        cut = (cuts[side] - a[axis]) / along[axis]
        gap = half_gap / length
        for s0, s1 in ((0.0, cut - gap), (cut + gap, 1.0)):
            if (s1 - s0) * length > 1.0:
                p0, p1 = a + along * s0 + 0.6 * inward, a + along * s1 + 0.6 * inward
                if kind == "hedge":
                    objects.hedge(mb, rng, p0, p1, h, (1.2, 2.2))
                else:
                    objects.fence(mb, rng, p0, p1, h)


def plaza(mb: MeshBuilder, rng: np.random.Generator, cfg: SimConfig, inner, h: float, ids) -> list[np.ndarray]:
    """Paved square: cobbles, trees in lawn pits, benches, lamps, a kiosk or two, maybe a fountain, bicycle racks."""
    x0, y0, x1, y1 = inner
    if x1 - x0 < 10.0 or y1 - y0 < 10.0:
        return []
    material = cfg.street.sidewalk_material
    paving = flat_grid(x0, x1, y0, y1, h + 0.005, 4.0)
    mb.add(paving, "sidewalk", material, sample_reflectivity(rng, material, len(paving[1])))
    # houses frame the square on some sides (facades towards it), the rest stays open to the streets
    frame = [rng.random() < 0.6 for _ in range(4)]
    depth = rng.uniform(9.0, 13.0)
    floors = int(rng.integers(3, 6))
    low, high = y0 + (depth if frame[0] else 0.0), y1 - (depth if frame[2] else 0.0)
    rects = (
        (x0, y0, x1, y0 + depth),
        (x1 - depth, low, x1, high),
        (x0, y1 - depth, x1, y1),
        (x0, low, x0 + depth, high),
    )
    for side, (built, rect) in enumerate(zip(frame, rects)):
        if built and rect[2] - rect[0] > 4.0 and rect[3] - rect[1] > 4.0:
            objects.building(mb, rng, rect, floors, rng.uniform(2.9, 3.4), (side + 2) % 4, h - 0.2)
    x0, x1 = x0 + (depth if frame[3] else 0.0), x1 - (depth if frame[1] else 0.0)
    y0, y1 = y0 + (depth if frame[0] else 0.0), y1 - (depth if frame[2] else 0.0)
    if x1 - x0 < 12.0 or y1 - y0 < 12.0:
        return []
    inset = rng.uniform(3.0, 5.0)
    ring = _loop(x0 + inset, y0 + inset, x1 - inset, y1 - inset)
    spacing = rng.uniform(8.0, 12.0)
    for k in range(4):  # trees in pits and benches along a ring inside the square
        a, b = ring[k], ring[(k + 1) % 4]
        length = float(np.linalg.norm(b - a))
        for t in np.arange(spacing / 2, length - 1.0, spacing):
            c = a + (b - a) * t / length
            pit = polygon_fan(
                c + 0.9 * np.column_stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)]),
                h + 0.02,
            )
            mb.add(pit, "terrain", "grass", sample_reflectivity(rng, "grass", len(pit[1])))
            objects.tree(mb, rng, c, h, rng.uniform(0.7, 1.0), clearance=2.5)
            if rng.random() < 0.5:
                yaw = float(np.arctan2(*(b - a)[::-1]))
                objects.other_object(mb, rng, c + (b - a) / length * spacing / 2, h, yaw)
    for corner in ring:
        objects.street_light(mb, rng, corner + rng.normal(0.0, 0.5, 2), h, rng.uniform(0.0, 2 * np.pi))
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    if rng.random() < 0.4:  # fountain basin (other-structure)
        radius = rng.uniform(1.5, 3.0)
        basin = cylinder(radius, h, h + rng.uniform(0.4, 0.8), 16, center=(cx, cy))
        mb.add(basin, "other-structure", "curb", sample_reflectivity(rng, "curb", len(basin[1])))
    for _ in range(int(rng.integers(1, 3))):  # kiosks / cafe pavilions (building)
        sx, sy = rng.uniform(3.0, 6.0), rng.uniform(3.0, 5.0)
        if x1 - x0 < 2 * (inset + sx) + 1.0 or y1 - y0 < 2 * (inset + sy) + 1.0:
            continue
        kx = rng.uniform(x0 + inset + sx, x1 - inset - sx)
        ky = rng.uniform(y0 + inset + sy, y1 - inset - sy)
        if abs(kx - cx) < 4.0 + sx and abs(ky - cy) < 4.0 + sy:
            continue
        objects.building(
            mb, rng, (kx - sx / 2, ky - sy / 2, kx + sx / 2, ky + sy / 2), 1, 3.0, 0, h - 0.2, relief=False
        )
    if rng.random() < cfg.objects.bicycle_prob:  # a bicycle rack at the edge of the square
        bx, by = rng.uniform(x0 + 2.0, x1 - 6.0), y0 + 1.5
        for k in range(int(rng.integers(2, 7))):
            mesh = objects.two_wheeler(rng, "bicycle", ids.take())
            add_mesh(mb, objects.place(mesh, np.pi / 2 + rng.normal(0, 0.1), (bx + 0.8 * k, by, h)))
    middle = 0.3 * min(x1 - x0, y1 - y0)
    return [ring, _loop(x0 + middle, y0 + middle, x1 - middle, y1 - middle)]


def parking_lot(mb: MeshBuilder, rng: np.random.Generator, cfg: SimConfig, inner, h: float, ids) -> list[np.ndarray]:
    """Parking lot: asphalt (parking) with painted stall lines, double rows of stalls between 6.5 m aisles,
    lawn islands with trees at the row ends, lamps; cars, some vans, at the place's occupancy."""
    x0, y0, x1, y1 = inner
    if x1 - x0 < 16.0 or y1 - y0 < 14.0:
        return []
    surface = flat_grid(x0, x1, y0, y1, h + 0.005, 4.0)
    mb.add(surface, "parking", "parking", sample_reflectivity(rng, "parking", len(surface[1])))
    if rng.random() < 0.8:  # a hedge round the lot, an entrance on each side
        cuts = (
            rng.uniform(x0 + 8, x1 - 8),
            rng.uniform(y0 + 7, y1 - 7),
            rng.uniform(x0 + 8, x1 - 8),
            rng.uniform(y0 + 7, y1 - 7),
        )
        _perimeter(mb, rng, inner, cuts, 3.5, h, "hedge")
    occupancy = rng.uniform(0.4, 0.9)
    stall_w, stall_d, aisle = rng.uniform(2.4, 2.7), 5.0, 6.5
    island = 2.5  # lawn islands with a tree at both ends of each double row
    lines = []
    y = y0 + aisle
    while y + 2 * stall_d <= y1 - aisle + 1e-6:
        for row, facing in ((0, -1.0), (1, 1.0)):
            ya = y + row * stall_d
            for x in np.arange(x0 + island + 1.0, x1 - island - 1.0 - stall_w, stall_w):
                lines.append((x, ya, x + 0.12, ya + stall_d))
                if rng.random() < occupancy:
                    c = (x + stall_w / 2, ya + stall_d / 2)
                    yaw = np.pi / 2 * facing + rng.normal(0.0, 0.03)
                    if rng.random() < 0.06:
                        mesh = objects.van(rng, "other-vehicle", ids.take())
                    else:
                        mesh = objects.car(rng, "car", ids.take(), kind=str(rng.choice(["sedan", "hatch", "suv"])))
                    add_mesh(mb, objects.place(mesh, float(yaw), (c[0], c[1], h)))
        for ex in (x0 + 0.5, x1 - 0.5 - island):
            pad = flat_grid(ex, ex + island, y + 0.5, y + 2 * stall_d - 0.5, h + 0.12, 2.0)
            kerb = merge(
                box([island, 0.15, 0.12], [ex + island / 2, y + 0.5, h + 0.06]),
                box([island, 0.15, 0.12], [ex + island / 2, y + 2 * stall_d - 0.5, h + 0.06]),
            )
            mb.add(pad, "terrain", "grass", sample_reflectivity(rng, "grass", len(pad[1])))
            mb.add(kerb, "sidewalk", "curb", sample_reflectivity(rng, "curb", len(kerb[1])))
            objects.tree(mb, rng, (ex + island / 2, y + stall_d), h + 0.12, rng.uniform(0.6, 0.9), clearance=2.2)
            if rng.random() < 0.5:
                objects.street_light(mb, rng, (ex + island / 2, y + stall_d + 1.5), h + 0.12, 0.0)
        y += 2 * stall_d + aisle
    if lines:
        paint = merge(
            *[quad((a, b, h + 0.008), (c, b, h + 0.008), (c, d, h + 0.008), (a, d, h + 0.008)) for a, b, c, d in lines]
        )
        mb.add(paint, "parking", "paint", sample_reflectivity(rng, "paint", len(paint[1])))
    return [_loop(x0 + 1.0, y0 + 1.0, x1 - 1.0, y1 - 1.0)]
