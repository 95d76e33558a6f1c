"""Object models of the simulated world in their own frame (x forward, z up, origin on the ground, centred).

Vehicles, people, riders, trees, bushes, poles, signs, fences and buildings, each a labelled TriangleMesh.
Sizes follow common street objects (KITTI object statistics: car ~3.9 x 1.6 x 1.5 m, pedestrian ~1.75 m).
"""

from __future__ import annotations

import numpy as np

from u4d_aug.data.sim.geometry import (
    MeshBuilder,
    TriangleMesh,
    blob,
    box,
    concat_meshes,
    cylinder,
    disc_y,
    extrude_profile,
    merge,
    polygon_fan,
    quad,
    sample_reflectivity,
    transform,
    wall_strip,
)

# person limb ids for the walking animation (vertex part ids, see `person`)
PART_RIGID, PART_LEFT_LEG, PART_RIGHT_LEG, PART_LEFT_ARM, PART_RIGHT_ARM = 0, 1, 2, 3, 4


def place(mesh: TriangleMesh, yaw: float, translation) -> TriangleMesh:
    """Copy of `mesh` rotated about z by yaw and translated."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
    vertices = mesh.vertices @ rot.T + np.asarray(translation, dtype=np.float32)
    return TriangleMesh(
        vertices.astype(np.float32),
        mesh.triangles,
        mesh.semantic,
        mesh.instance,
        mesh.material,
        mesh.reflectivity,
    )


def _wheels(mb: MeshBuilder, rng, length, width, radius, label, instance, axle_front=None, axle_rear=None):
    front = axle_front if axle_front is not None else length / 2 - radius * 1.6
    rear = axle_rear if axle_rear is not None else -length / 2 + radius * 1.6
    parts = [
        transform(disc_y(radius, 0.22), 0.0, (x, y, radius))
        for x in (front, rear)
        for y in (-1, 1)
        for y in [y * (width / 2 - 0.12)]
    ]
    wheels = merge(*parts)
    mb.add(wheels, label, "tire", sample_reflectivity(rng, "tire", len(wheels[1])), instance)


def car(rng: np.random.Generator, label: str = "car", instance: int = 0, kind: str = "sedan") -> TriangleMesh:
    """Passenger car: convex body profile, narrower glass cabin, four wheels (sedan | hatch | suv)."""
    length = {"sedan": rng.uniform(4.2, 4.9), "hatch": rng.uniform(3.7, 4.2), "suv": rng.uniform(4.4, 4.9)}[kind]
    width = rng.uniform(1.7, 1.9)
    height = {
        "sedan": rng.uniform(1.38, 1.5),
        "hatch": rng.uniform(1.45, 1.55),
        "suv": rng.uniform(1.65, 1.8),
    }[kind]
    clearance, belt = 0.25, height * rng.uniform(0.58, 0.64)
    half = length / 2
    body = np.array(
        [
            [-half, clearance],
            [half - 0.05, clearance],
            [half, belt - 0.25],
            [half - 0.25, belt],
            [-half + 0.1, belt],
            [-half, belt - 0.15],
        ]
    )
    mb = MeshBuilder()
    paint = sample_reflectivity(rng, "car_paint")[0]
    b = extrude_profile(body, width)
    mb.add(b, label, "car_paint", paint * (1 + 0.05 * rng.standard_normal(len(b[1]))), instance)
    rear_slope = 0.25 if kind == "hatch" else 0.6
    cabin = np.array(
        [[-half + 0.35, belt], [half - 1.0, belt], [half - 1.75, height], [-half + 0.35 + rear_slope, height]]
    )
    if kind == "suv":
        cabin = np.array([[-half + 0.15, belt], [half - 1.1, belt], [half - 1.7, height], [-half + 0.25, height]])
    cv, ct = extrude_profile(cabin, width - 0.16)
    roof_like = np.abs(np.cross(cv[ct[:, 1]] - cv[ct[:, 0]], cv[ct[:, 2]] - cv[ct[:, 0]])[:, 2])
    normal_z = roof_like / np.maximum(
        np.linalg.norm(np.cross(cv[ct[:, 1]] - cv[ct[:, 0]], cv[ct[:, 2]] - cv[ct[:, 0]]), axis=1), 1e-9
    )
    roof = normal_z > 0.95
    mb.add((cv, ct[roof]), label, "car_paint", paint, instance)
    mb.add(
        (cv, ct[~roof]),
        label,
        "car_glass",
        sample_reflectivity(rng, "car_glass", int((~roof).sum())),
        instance,
    )
    _wheels(mb, rng, length, width, 0.32, label, instance)
    return mb.build()


def van(rng: np.random.Generator, label: str = "other-vehicle", instance: int = 0) -> TriangleMesh:
    """Van / minibus (SemanticKITTI other-vehicle): tall box body with a sloped nose."""
    length, width, height = rng.uniform(4.8, 5.9), rng.uniform(1.9, 2.05), rng.uniform(1.95, 2.5)
    half = length / 2
    profile = np.array(
        [
            [-half, 0.3],
            [half, 0.3],
            [half, 1.0],
            [half - 0.9, height - 0.05],
            [half - 1.1, height],
            [-half, height],
        ]
    )
    mb = MeshBuilder()
    b = extrude_profile(profile, width)
    mb.add(b, label, "car_paint", sample_reflectivity(rng, "car_paint", len(b[1])) + 0.08, instance)
    glass = quad(
        [half - 0.05, -width / 2 + 0.1, 1.1],
        [half - 0.05, width / 2 - 0.1, 1.1],
        [half - 0.85, width / 2 - 0.1, height - 0.1],
        [half - 0.85, -width / 2 + 0.1, height - 0.1],
    )
    mb.add((glass[0] + [0.02, 0, 0], glass[1]), label, "car_glass", 0.03, instance)
    _wheels(mb, rng, length, width, 0.35, label, instance)
    return mb.build()


def truck(rng: np.random.Generator, label: str = "truck", instance: int = 0) -> TriangleMesh:
    """Truck: cab and a cargo box, six wheels."""
    length, width = rng.uniform(6.5, 10.0), rng.uniform(2.3, 2.5)
    cab_len, height = 2.2, rng.uniform(2.9, 3.6)
    mb = MeshBuilder()
    cab = box([cab_len, width, 2.6], [length / 2 - cab_len / 2, 0, 0.6 + 1.3])
    cargo = box([length - cab_len - 0.2, width, height - 0.7], [-cab_len / 2 - 0.1, 0, 0.7 + (height - 0.7) / 2])
    mb.add(cab, label, "car_paint", sample_reflectivity(rng, "car_paint", 12) + 0.1, instance)
    mb.add(cargo, label, "plastic", sample_reflectivity(rng, "plastic", 12) + 0.1, instance)
    _wheels(mb, rng, length, width, 0.48, label, instance, length / 2 - 1.2, -length / 2 + 1.4)
    mid = merge(*[transform(disc_y(0.48, 0.3), 0.0, (-length / 2 + 2.5, y, 0.48)) for y in (-1.0, 1.0)])
    mb.add(mid, label, "tire", 0.05, instance)
    return mb.build()


def two_wheeler(rng: np.random.Generator, label: str, instance: int = 0, motor: bool = False) -> TriangleMesh:
    """Bicycle or motorcycle without rider: two wheels, a frame, handlebar."""
    mb = MeshBuilder()
    radius = 0.36 if not motor else 0.32
    wheelbase = rng.uniform(1.0, 1.1) if not motor else rng.uniform(1.35, 1.5)
    wheels = merge(
        *[
            transform(disc_y(radius, 0.06 if not motor else 0.14, 12), 0.0, (x, 0, radius))
            for x in (-wheelbase / 2, wheelbase / 2)
        ]
    )
    mb.add(wheels, label, "tire" if motor else "spokes", 0.1, instance)
    if motor:
        body = box([wheelbase * 0.8, 0.35, 0.45], [0, 0, radius + 0.3])
        mb.add(body, label, "car_paint", sample_reflectivity(rng, "car_paint", 12) + 0.1, instance)
    frame = merge(
        box([wheelbase * 0.9, 0.05, 0.05], [0, 0, radius + 0.25]),
        box([0.05, 0.05, 0.5], [-wheelbase * 0.15, 0, radius + 0.1]),
        box([0.05, 0.5, 0.04], [wheelbase * 0.4, 0, radius + 0.55]),
    )
    mb.add(frame, label, "metal", 0.3, instance)
    return mb.build()


def person(rng: np.random.Generator, label: str = "person", instance: int = 0, seated: bool = False):
    """Pedestrian (seated rider when `seated`): legs, torso, arms, head -> (mesh, part id per vertex)."""
    height = rng.uniform(1.6, 1.9)
    leg, torso_h = 0.47 * height, 0.32 * height
    hip = leg if not seated else 0.0
    mb = MeshBuilder()
    parts = []
    clothes = sample_reflectivity(rng, "clothes")[0]
    for side, pid in ((-1, PART_LEFT_LEG), (1, PART_RIGHT_LEG)):
        if seated:
            continue
        lg = box([0.15, 0.15, leg], [0, side * 0.1, leg / 2])
        mb.add(lg, label, "clothes", clothes, instance)
        parts.append(np.full(8, pid))
    torso = cylinder(0.17, hip, hip + torso_h, segments=8)
    torso = (torso[0] * [0.75, 1.2, 1.0], torso[1])
    mb.add(torso, label, "clothes", clothes * 1.1, instance)
    parts.append(np.zeros(len(torso[0]), np.int64))
    for side, pid in ((-1, PART_LEFT_ARM), (1, PART_RIGHT_ARM)):
        arm = box([0.09, 0.09, 0.6 * torso_h + 0.2], [0, side * 0.26, hip + torso_h - (0.6 * torso_h + 0.2) / 2])
        mb.add(arm, label, "clothes", clothes, instance)
        parts.append(np.full(8, pid if not seated else PART_RIGID))
    head = blob(rng, [0.1, 0.09, 0.12], [0, 0, hip + torso_h + 0.15], subdivisions=1, roughness=0.05)
    mb.add(head, label, "skin", sample_reflectivity(rng, "skin")[0], instance)
    parts.append(np.zeros(len(head[0]), np.int64))
    return mb.build(), np.concatenate(parts)


def rider(rng: np.random.Generator, label: str, instance: int, motor: bool):
    """Bicyclist / motorcyclist: the two-wheeler and a seated person under one label (as SemanticKITTI)."""
    bike = two_wheeler(rng, label, instance, motor=motor)
    body, _ = person(rng, label, instance, seated=True)
    seat_height = 0.95 if not motor else 0.85
    body = place(body, 0.0, (-0.15, 0.0, seat_height))
    legs = MeshBuilder()
    legs.add(
        merge(box([0.14, 0.14, 0.7], [0.05, -0.12, 0.55]), box([0.14, 0.14, 0.7], [0.05, 0.12, 0.55])),
        label,
        "clothes",
        0.2,
        instance,
    )
    mesh = concat_meshes([bike, body, legs.build()])
    return mesh, np.zeros(len(mesh.vertices), np.int64)


def tree(
    mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, scale: float = 1.0, clearance: float = 0.0
) -> None:
    """Street/yard tree: a trunk and 1-3 irregular canopy blobs (leaves are porous: penetration in MATERIALS);
    the canopy is lifted so that its lowest point clears `clearance` above the ground (street trees, ~4 m)."""
    trunk_h = rng.uniform(1.4, 2.8) * scale
    radius = rng.uniform(0.07, 0.18) * scale
    x, y = xy
    tilt = rng.normal(0, 0.1, 2)
    canopy_r = rng.uniform(2.2, 4.5) * scale
    center = ground_z + trunk_h + canopy_r * rng.uniform(0.5, 0.8)
    flatten = rng.uniform(0.6, 0.9) if clearance > 0 else rng.uniform(0.75, 1.15)
    blobs = []
    for k in range(int(rng.integers(1, 4))):
        offset = np.append(rng.normal(0, canopy_r * 0.35, 2) + tilt, rng.normal(0, 0.3) + (0.0 if k == 0 else 0.4))
        radii = canopy_r * rng.uniform(0.65, 1.0, 3) * [1, 1, flatten]
        blobs.append(blob(rng, radii, [x + offset[0], y + offset[1], center + offset[2]], 2, 0.22))
    lowest = min(float(b[0][:, 2].min()) for b in blobs)
    lift = max(0.0, ground_z + clearance - lowest)
    trunk_top = trunk_h + lift + 0.8
    t = cylinder(radius, ground_z, ground_z + trunk_top, segments=8, center=(x, y))
    t[0][:, :2] += np.outer((t[0][:, 2] - ground_z) / trunk_top, tilt)
    with mb.rigid((x, y)):
        mb.add(t, "trunk", "bark", sample_reflectivity(rng, "bark", len(t[1])))
        leaves_refl = sample_reflectivity(rng, "leaves")[0]
        for vertices, triangles in blobs:
            mb.add(
                (vertices + [0.0, 0.0, lift], triangles),
                "vegetation",
                "leaves",
                leaves_refl * (1 + 0.08 * rng.standard_normal(len(triangles))),
            )


def bush(mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, size: float = 1.0) -> None:
    """Low shrub: one flattened blob sitting on the ground."""
    radii = size * rng.uniform(0.5, 1.2, 3) * [1, 1, 0.7]
    b = blob(rng, radii, [xy[0], xy[1], ground_z + radii[2] * 0.7], subdivisions=1, roughness=0.25)
    mb.add(b, "vegetation", "hedge", sample_reflectivity(rng, "hedge", len(b[1])))


def hedge(mb: MeshBuilder, rng: np.random.Generator, p0, p1, ground_z: float, height_range=(1.0, 2.5)) -> None:
    """Hedge along p0 -> p1: a row of overlapping box-like blobs ~1 m deep, `height_range` m tall."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = np.linalg.norm(p1 - p0)
    height = rng.uniform(*height_range)
    refl = sample_reflectivity(rng, "hedge")[0]
    n = max(1, int(length / 1.6))
    for k in range(n):
        c = p0 + (p1 - p0) * (k + 0.5) / n
        b = blob(rng, [length / n * 0.65, 0.5, height / 2], [c[0], c[1], ground_z + height / 2], 1, 0.12)
        yaw = np.arctan2(*(p1 - p0)[::-1])
        b = transform((b[0] - [c[0], c[1], 0], b[1]), yaw, (c[0], c[1], 0))
        mb.add(b, "vegetation", "hedge", refl * (1 + 0.08 * rng.standard_normal(len(b[1]))))


def fence(mb: MeshBuilder, rng: np.random.Generator, p0, p1, ground_z: float) -> None:
    """Fence or low wall along p0 -> p1 (SemanticKITTI fence covers both): slatted, bars or solid."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    direction = p1 - p0
    length = float(np.linalg.norm(direction))
    yaw = float(np.arctan2(direction[1], direction[0]))
    kind = rng.choice(["slats", "bars", "wall"], p=[0.4, 0.25, 0.35])
    height = rng.uniform(0.9, 1.6) if kind != "wall" else rng.uniform(0.5, 1.3)
    parts = []
    pieces = np.linspace(0.0, length, max(1, int(np.ceil(length / 2.5))) + 1)  # <= 2.5 m: bends with a warp
    if kind == "wall":
        thickness = rng.uniform(0.15, 0.3)
        parts += [box([b - a, thickness, height], [(a + b) / 2, 0, height / 2]) for a, b in zip(pieces, pieces[1:])]
        material = "curb"
    else:
        width, gap = (0.09, rng.uniform(0.03, 0.08)) if kind == "slats" else (0.03, rng.uniform(0.09, 0.14))
        xs = np.arange(width / 2, length, width + gap)
        parts += [box([width, 0.025, height], [x, 0, height / 2], bottom=False) for x in xs]
        parts += [
            box([b - a, 0.04, 0.06], [(a + b) / 2, 0.03, z])
            for z in (0.2, height - 0.15)
            for a, b in zip(pieces, pieces[1:])
        ]
        material = "fence" if kind == "slats" else "metal"
    part = transform(merge(*parts), yaw, (p0[0], p0[1], ground_z))
    mb.add(part, "fence", material, sample_reflectivity(rng, material, len(part[1])))


def shed(mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, yaw: float, footprint) -> None:
    """Garden shed or bin shelter (SemanticKITTI other-structure): a wooden or metal box with an overhanging roof."""
    sx, sy = footprint
    height = rng.uniform(1.3, 2.4)
    material = "fence" if rng.random() < 0.6 else "metal"
    walls = box([sx, sy, height], [0.0, 0.0, height / 2], bottom=False)
    roof = box([sx + 0.3, sy + 0.3, 0.08], [0.0, 0.0, height + 0.04])
    part = transform(merge(walls, roof), yaw, (xy[0], xy[1], ground_z))
    mb.add(part, "other-structure", material, sample_reflectivity(rng, material, len(part[1])))


def street_light(mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, arm_yaw: float) -> None:
    """Street light: tall pole with an arm and a lamp head (all SemanticKITTI pole)."""
    height = rng.uniform(5.5, 8.5)
    radius = rng.uniform(0.07, 0.12)
    p = cylinder(radius, ground_z, ground_z + height, 8, center=xy)
    arm_len = rng.uniform(0.8, 2.0)
    arm = transform(box([arm_len, 0.06, 0.06], [arm_len / 2, 0, height - 0.1]), arm_yaw, (xy[0], xy[1], ground_z))
    head = transform(box([0.5, 0.25, 0.15], [arm_len, 0, height - 0.2]), arm_yaw, (xy[0], xy[1], ground_z))
    part = merge(p, arm, head)
    mb.add(part, "pole", "metal", sample_reflectivity(rng, "metal", len(part[1])))


def traffic_sign(
    mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, face_yaw: float, back: str | None = None
) -> None:
    """Traffic sign: thin pole (pole) and one or two retro-reflective plates (traffic-sign); `back` names the
    material of the plates' backs (None: retro-reflective both sides, as the default world has them)."""
    with mb.rigid(xy):
        _traffic_sign(mb, rng, xy, ground_z, face_yaw, back)


def traffic_light(mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, face_yaw: float) -> None:
    """Traffic light: a pole (pole) carrying one or two signal heads (SemanticKITTI labels them traffic-sign)."""
    with mb.rigid(xy):
        height = rng.uniform(2.8, 3.6)
        p = cylinder(0.07, ground_z, ground_z + height + 0.2, 8, center=xy)
        mb.add(p, "pole", "metal", sample_reflectivity(rng, "metal", len(p[1])))
        heads = [box([0.3, 0.35, 1.0], [0.2, 0.0, height - 0.3])]
        if rng.random() < 0.5:  # a second head lower down for pedestrians
            heads.append(box([0.25, 0.3, 0.6], [0.18, 0.0, 2.1]))
        part = transform(merge(*heads), face_yaw, (xy[0], xy[1], ground_z))
        mb.add(part, "traffic-sign", "plastic", sample_reflectivity(rng, "plastic", len(part[1])))


def _traffic_sign(
    mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, face_yaw: float, back: str | None = None
) -> None:
    height = rng.uniform(2.2, 3.0)
    p = cylinder(0.04, ground_z, ground_z + height, 6, center=xy)
    mb.add(p, "pole", "metal", sample_reflectivity(rng, "metal", len(p[1])))
    for k in range(int(rng.integers(1, 3))):
        size = rng.uniform(0.5, 0.8)
        z = ground_z + height - size / 2 - k * (size + 0.1)
        shape = rng.choice(["disc", "square", "triangle"])
        n = {"disc": 8, "square": 4, "triangle": 3}[shape]
        angles = np.linspace(0, 2 * np.pi, n, endpoint=False) + (np.pi / 4 if n == 4 else np.pi / 2)
        outline = np.column_stack([np.cos(angles), np.sin(angles)]) * size / 2
        plate = polygon_fan(outline, 0.0)  # in x-y, then stood up facing +x
        v = plate[0][:, [2, 0, 1]] + [0.05, 0, 0]
        rear = (v - [0.02, 0, 0], plate[1][:, ::-1])
        if back is None:
            part = transform(merge((v, plate[1]), rear), face_yaw, (xy[0], xy[1], z))
            mb.add(part, "traffic-sign", "sign", sample_reflectivity(rng, "sign", len(part[1])))
        else:
            front = transform((v, plate[1]), face_yaw, (xy[0], xy[1], z))
            mb.add(front, "traffic-sign", "sign", sample_reflectivity(rng, "sign", len(front[1])))
            rear = transform(rear, face_yaw, (xy[0], xy[1], z))
            mb.add(rear, "traffic-sign", back, sample_reflectivity(rng, back, len(rear[1])))


def other_object(mb: MeshBuilder, rng: np.random.Generator, xy, ground_z: float, yaw: float) -> None:
    """Street clutter labelled other-object: trash bin, bollard pair, utility box, bench."""
    kind = rng.choice(["bin", "bollards", "box", "bench"])
    if kind == "bin":
        part = cylinder(0.3, 0.0, 1.0, 8)
    elif kind == "bollards":
        part = merge(*[cylinder(0.08, 0.0, 0.9, 6, center=(0, dy)) for dy in (-0.9, 0.0, 0.9)])
    elif kind == "box":
        part = box([0.6, 0.4, 1.3], [0, 0, 0.65])
    else:
        part = merge(
            box([0.5, 1.8, 0.06], [0, 0, 0.45]),
            box([0.06, 1.8, 0.4], [-0.22, 0, 0.7]),
            box([0.4, 0.06, 0.45], [0, -0.85, 0.22]),
            box([0.4, 0.06, 0.45], [0, 0.85, 0.22]),
        )
    part = transform(part, yaw, (xy[0], xy[1], ground_z))
    mb.add(part, "other-object", "plastic", sample_reflectivity(rng, "plastic", len(part[1])))


def building(
    mb: MeshBuilder,
    rng: np.random.Generator,
    footprint,
    floors: int,
    floor_height: float,
    front_side: int,
    base_z: float,
    relief: bool = True,
) -> None:
    """Box building on an axis-aligned footprint (x0, y0, x1, y1); the street side (0:-y 1:+x 2:+y 3:-x)
    gets recessed windows and balconies, the roof is flat or gabled. A warped builder shears it with its lot (a
    bending street gives skewed footprints whose side walls stay parallel to the cross streets)."""
    x0, y0, x1, y1 = footprint
    height = floors * floor_height + rng.uniform(0.3, 1.0)
    facade = sample_reflectivity(rng, "facade")[0]
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    for side in range(4):
        a, b = corners[side], corners[(side + 1) % 4]
        if side == front_side and relief:
            _facade(mb, rng, a, b, base_z, floors, floor_height, height, facade)
        else:
            w = wall_strip(np.array([a, b]), base_z, base_z + height)
            mb.add(w, "building", "facade", facade * (1 + 0.05 * rng.standard_normal(len(w[1]))))
    if rng.random() < 0.5:
        roof = polygon_fan(corners, base_z + height)
        mb.add(roof, "building", "roof", sample_reflectivity(rng, "roof", 2))
    else:  # gable along the longer side
        rise = rng.uniform(2.0, 4.0)
        along_x = (x1 - x0) >= (y1 - y0)
        span = (y1 - y0) if along_x else (x1 - x0)
        profile = np.array([[-span / 2, 0.0], [span / 2, 0.0], [0.0, rise]])
        v, t = extrude_profile(profile, (x1 - x0) if along_x else (y1 - y0))
        v = v[:, [1, 0, 2]] if along_x else v  # ridge along x: profile across y
        v = v + [(x0 + x1) / 2, (y0 + y1) / 2, base_z + height]
        mb.add((v, t), "building", "roof", sample_reflectivity(rng, "roof", len(t)))


def _facade(mb, rng, a, b, base_z, floors, floor_height, height, refl) -> None:
    """Street facade a -> b (outside on the right of a->b when walking counter-clockwise): a panel grid with
    recessed glass windows and some balconies."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    along = b - a
    length = float(np.linalg.norm(along))
    u = along / length
    n_out = np.array([u[1], -u[0]])  # outward normal for a counter-clockwise footprint
    win_w, pitch = rng.uniform(1.0, 1.6), rng.uniform(2.6, 3.6)
    cols = max(1, int((length - 1.0) // pitch))
    margin = (length - cols * pitch) / 2
    sill, win_h, depth = 0.9, rng.uniform(1.2, 1.6), rng.uniform(0.12, 0.25)
    xs = sorted({0.0, length} | {margin + k * pitch + (pitch - win_w) / 2 + d for k in range(cols) for d in (0, win_w)})
    zs = sorted({0.0, height} | {f * floor_height + d for f in range(floors) for d in (sill, sill + win_h)})
    zs = [z for z in zs if z <= height]
    wall, glass, reveal = [], [], []
    window_cols = {
        i
        for i in range(len(xs) - 1)
        if any(abs(xs[i] - (margin + k * pitch + (pitch - win_w) / 2)) < 1e-6 for k in range(cols))
    }
    window_rows = {
        j for j in range(len(zs) - 1) if any(abs(zs[j] - (f * floor_height + sill)) < 1e-6 for f in range(floors))
    }

    def pt(s, z, d=0.0):
        xy = a + u * s - n_out * d
        return [xy[0], xy[1], base_z + z]

    for i in range(len(xs) - 1):
        for j in range(len(zs) - 1):
            s0, s1, z0, z1 = xs[i], xs[i + 1], zs[j], zs[j + 1]
            if i in window_cols and j in window_rows:
                glass.append(quad(pt(s0, z0, depth), pt(s1, z0, depth), pt(s1, z1, depth), pt(s0, z1, depth)))
                reveal += [
                    quad(pt(s0, z0), pt(s0, z0, depth), pt(s0, z1, depth), pt(s0, z1)),
                    quad(pt(s1, z0, depth), pt(s1, z0), pt(s1, z1), pt(s1, z1, depth)),
                    quad(pt(s0, z0), pt(s1, z0), pt(s1, z0, depth), pt(s0, z0, depth)),
                    quad(pt(s0, z1, depth), pt(s1, z1, depth), pt(s1, z1), pt(s0, z1)),
                ]
            else:
                wall.append(quad(pt(s0, z0), pt(s1, z0), pt(s1, z1), pt(s0, z1)))
    w = merge(*wall, *reveal)
    mb.add(w, "building", "facade", refl * (1 + 0.05 * rng.standard_normal(len(w[1]))))
    g = merge(*glass)
    mb.add(g, "building", "glass", sample_reflectivity(rng, "glass", len(g[1])))
    if floors >= 2 and rng.random() < 0.4:  # balconies on upper floors
        for f in range(1, floors):
            for k in range(cols):
                if rng.random() < 0.5:
                    continue
                s = margin + k * pitch + pitch / 2
                c = a + u * s + n_out * 0.6
                bal = transform(
                    box([pitch * 0.8, 1.2, 1.0], [0, 0, 0.5]),
                    float(np.arctan2(u[1], u[0])),
                    (c[0], c[1], base_z + f * floor_height),
                )
                mb.add(bal, "building", "facade", refl)
