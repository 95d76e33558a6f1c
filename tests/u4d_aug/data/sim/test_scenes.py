"""Street types of the simulated world (u4d_aug/data/sim/scenes.py, blocks.py): choice per place, layouts, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from u4d_aug.config import load_config
from u4d_aug.data.sensors import hdl64
from u4d_aug.data.sim.config import SimConfig, StreetTypeWeights
from u4d_aug.data.sim.geometry import RAW
from u4d_aug.data.sim.scenes import STREET_TYPES, place_street_type, street_type_config
from u4d_aug.data.sim.world import block_sides
from u4d_aug.data.sim.writer import build_sequence
from u4d_aug.errors import InputError

REPO = Path(__file__).resolve().parents[4]
TINY = REPO / "configs" / "sim" / "tiny.yaml"


def _only(kind: str, *overrides: str) -> SimConfig:
    """The tiny world with every place of street type `kind`."""
    weights = [f"street_types.{name}={1.0 if name == kind else 0.0}" for name in STREET_TYPES]
    return load_config(SimConfig, TINY, [*weights, *overrides])


def _surface_labels(seq, xy_lattice: np.ndarray) -> np.ndarray:
    """Raw label of the ground surface under (N, 2) lattice points: rays cast down from 0.6 m above the ground."""
    mesh, warp = seq.world.mesh, seq.world.network.warp
    xy = warp.points(xy_lattice)
    z = warp.hills(xy) + 0.6
    rays = np.column_stack([xy, z, np.zeros((len(xy), 2)), -np.ones(len(xy))]).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices), o3d.core.Tensor(mesh.triangles))
    out = scene.cast_rays(o3d.core.Tensor(rays))
    prim = out["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(out["t_hit"].numpy())
    return np.where(hit, mesh.semantic[np.where(hit, prim, 0)], 0)


def _side_points(seq, offset_fn, per_side: int = 12) -> np.ndarray:
    """Lattice points along every block side of the world, `offset_fn(line, side) ` metres in from the curb."""
    net, pts = seq.world.network, []
    for block in seq.world.blocks:
        i, j = block.index
        x0, y0, x1, y1 = block.curb
        margin = net.corner_radius + 2.0
        for side, (line, line_side) in enumerate(block_sides(net, i, j)):
            off = offset_fn(line, line_side)
            if off is None:
                continue
            along = np.linspace(0.0, 1.0, per_side + 2)[1:-1]
            if side % 2 == 0 and x1 - x0 > 2 * margin:
                xs = x0 + margin + along * (x1 - x0 - 2 * margin)
                ys = np.full(per_side, y0 + off if side == 0 else y1 - off)
            elif side % 2 == 1 and y1 - y0 > 2 * margin:
                ys = y0 + margin + along * (y1 - y0 - 2 * margin)
                xs = np.full(per_side, x1 - off if side == 1 else x0 + off)
            else:
                continue
            pts.append(np.column_stack([xs, ys]))
    return np.concatenate(pts)


def _share(labels: np.ndarray, *names: str) -> float:
    return float(np.isin(labels, [RAW[n] for n in names]).mean())


def _inner_points(seq, use: str, count: int = 400) -> np.ndarray:
    """Random lattice points inside the blocks of one use (blocks with walks other than their sidewalk)."""
    rng = np.random.default_rng(0)
    chosen = [b for b in seq.world.blocks if b.paths]
    assert chosen, f"no {use} block in this place"
    pts = []
    for block in chosen:
        x0, y0, x1, y1 = block.inner
        pts.append(np.column_stack([rng.uniform(x0 + 1, x1 - 1, count), rng.uniform(y0 + 1, y1 - 1, count)]))
    return np.concatenate(pts)


# ------------------------------------------------------------------------------------------------------------
# choice per place, config, errors


def test_default_world_is_residential_without_a_draw() -> None:
    cfg = SimConfig()
    assert place_street_type(0, 0, cfg.street_types) == "residential"
    assert street_type_config(cfg, "residential") is cfg


def test_street_type_per_place_is_seeded_and_follows_the_weights() -> None:
    weights = StreetTypeWeights(residential=1.0, park=1.0, plaza=2.0)
    first = [place_street_type(7, k, weights) for k in range(400)]
    assert first == [place_street_type(7, k, weights) for k in range(400)]  # reproducible
    assert first != [place_street_type(8, k, weights) for k in range(400)]  # another seed, other places
    counts = {kind: first.count(kind) for kind in STREET_TYPES}
    assert set(k for k, c in counts.items() if c) == {"residential", "park", "plaza"}
    assert abs(counts["plaza"] / 400 - 0.5) < 0.08 and abs(counts["park"] / 400 - 0.25) < 0.07


def test_bad_street_types_are_refused_naming_the_key() -> None:
    with pytest.raises(InputError, match="unknown config key 'street_types.roundabouts'"):
        load_config(SimConfig, None, ["street_types.roundabouts=1"])
    with pytest.raises(InputError, match="street_types.park' must be >= 0"):
        load_config(SimConfig, None, ["street_types.park=-0.5"])
    with pytest.raises(InputError, match="'street_types'"):
        load_config(SimConfig, None, ["street_types.residential=0"])
    with pytest.raises(InputError, match="street type 'alley'"):
        street_type_config(SimConfig(), "alley")
    with pytest.raises(InputError, match="lots.park_block_prob"):
        load_config(SimConfig, None, ["lots.park_block_prob=-1"])


def test_varied_preset_mixes_every_type() -> None:
    cfg = load_config(SimConfig, REPO / "configs" / "sim" / "varied.yaml", [])
    kinds = {place_street_type(0, k, cfg.street_types) for k in range(100)}
    assert kinds == set(STREET_TYPES)
    for kind in STREET_TYPES:  # every type's config is valid
        assert isinstance(street_type_config(cfg, kind), SimConfig)


def test_place_config_is_recorded_on_the_sequence() -> None:
    seq = build_sequence(2, 1, 2, hdl64(), _only("park"))
    assert seq.street_type == "park"
    assert seq.cfg.street.grass_strip_prob == 0.9 and seq.cfg.lots.park_block_prob == 0.3


# ------------------------------------------------------------------------------------------------------------
# layouts: ground classes in the expected places


def test_residential_sidewalk_then_road() -> None:
    seq = build_sequence(1, 0, 2, hdl64(), _only("residential"))
    walk = _surface_labels(
        seq, _side_points(seq, lambda line, s: line.sidewalk[s] - 0.4 if not line.grass[s] else None)
    )
    assert _share(walk, "sidewalk") > 0.9
    road = _surface_labels(seq, _side_points(seq, lambda line, s: -line.parking[s] - 0.8))
    assert _share(road, "road", "lane-marking") > 0.9


def test_park_lawn_strip_between_road_and_sidewalk() -> None:
    seq = build_sequence(1, 0, 2, hdl64(), _only("park"))
    lines = seq.world.network.xs + seq.world.network.ys
    assert np.mean([g > 0 for line in lines for g in line.grass]) > 0.7
    assert 0.08 <= seq.world.network.curb_height <= 0.14
    strip = _surface_labels(seq, _side_points(seq, lambda line, s: line.grass[s] / 2 if line.grass[s] >= 1.5 else None))
    assert _share(strip, "terrain") > 0.8  # the lawn strip next to the kerb
    paving = _surface_labels(
        seq, _side_points(seq, lambda line, s: (line.grass[s] + line.sidewalk[s]) / 2 + 0.25 if line.grass[s] else None)
    )
    assert _share(paving, "sidewalk") > 0.8  # then the footway
    park = _surface_labels(seq, _inner_points(seq, "park"))
    assert _share(park, "terrain") > 0.6 and _share(park, "sidewalk", "other-ground") > 0.02  # lawn and paths


def test_parking_lots_and_driveways() -> None:
    seq = build_sequence(3, 0, 2, hdl64(), _only("parking", "lots.parking_block_prob=1"))
    assert 0.04 <= seq.world.network.curb_height <= 0.10
    lot = _surface_labels(seq, _inner_points(seq, "parking"))
    assert _share(lot, "parking", "car", "other-vehicle") > 0.8
    assert _share(lot, "car") > 0.1  # parked cars fill the stalls
    # driveways: every lot a house; without driveways no parking lies inside a block's lots, with them some does
    houses = "lots.kind_weights=[1, 0, 0, 0, 0]"
    for prob, expected in ((0.0, 0.0), (1.0, 0.02)):
        seq = build_sequence(3, 0, 2, hdl64(), _only("residential", houses, f"lots.driveway_prob={prob}"))
        front = _side_points(seq, lambda line, s: line.sidewalk[s] + 1.0, per_side=40)  # 1 m into the lots
        share = _share(_surface_labels(seq, front), "parking", "car")
        assert share > expected if prob else share == 0.0, (prob, share)


def test_plaza_is_paved_with_people() -> None:
    seq = build_sequence(2, 0, 3, hdl64(), _only("plaza", "lots.plaza_block_prob=1"))
    square = _surface_labels(seq, _inner_points(seq, "plaza"))
    assert _share(square, "sidewalk") > 0.75
    assert seq.cfg.street.sidewalk_material == "cobble" and seq.world.network.curb_height <= 0.08
    people = [a for a in seq.agents if a.kind == "person"]
    assert len(people) >= 5 and any(a.z > seq.world.network.curb_height for a in people)  # some walk the square


def test_arterial_wide_multilane_roads() -> None:
    seq = build_sequence(4, 0, 2, hdl64(), _only("arterial", "street.main_street_prob=1"))
    lines = seq.world.network.xs + seq.world.network.ys
    lanes = {line.lanes_per_direction for line in lines}
    assert lanes <= {2, 3} and 3 in lanes
    assert all(3.3 <= line.lane_width <= 3.7 for line in lines)
    road = _surface_labels(seq, _side_points(seq, lambda line, s: -line.half_road + 0.8))  # the inner lane
    assert _share(road, "road", "lane-marking", "other-ground", "terrain") > 0.95
    assert (seq.world.mesh.semantic == RAW["traffic-sign"]).sum() > 0  # traffic lights and signs


def test_intersection_short_blocks_and_signals() -> None:
    seq = build_sequence(5, 0, 2, hdl64(), _only("intersection"))
    spacing = np.diff([line.position for line in seq.world.network.xs])
    assert np.all((spacing >= 45.0) & (spacing <= 80.0))
    assert seq.cfg.agents.ego_turn_prob == 0.7


def test_green_places_hold_more_vegetation() -> None:
    green = build_sequence(6, 0, 2, hdl64(), _only("green")).world.mesh
    base = build_sequence(6, 0, 2, hdl64(), _only("residential")).world.mesh
    plants = [RAW["vegetation"], RAW["trunk"]]
    assert np.isin(green.semantic, plants).sum() > 1.3 * np.isin(base.semantic, plants).sum()  # same streets


@pytest.mark.parametrize("kind", STREET_TYPES)
def test_every_type_has_people_cyclists_and_vehicles(kind: str) -> None:
    moving, standing, parked, two_wheelers = set(), 0, 0, 0
    for index in range(3):
        seq = build_sequence(9, index, 3, hdl64(), _only(kind))
        moving |= {a.kind for a in seq.agents if a.mesh.semantic[0] >= 252}
        standing += sum(a.mesh.semantic[0] == RAW["person"] for a in seq.agents)
        mesh = seq.world.mesh
        parked += len(
            np.unique(mesh.instance[np.isin(mesh.semantic, [RAW["car"], RAW["truck"], RAW["other-vehicle"]])])
        )
        two_wheelers += len(np.unique(mesh.instance[np.isin(mesh.semantic, [RAW["bicycle"], RAW["motorcycle"]])]))
    assert "person" in moving and {"car", "truck", "van"} & moving, (kind, moving)
    assert {"bicyclist", "motorcyclist"} & moving, (kind, moving)
    assert standing > 0 and parked > 0 and two_wheelers > 0, (kind, standing, parked, two_wheelers)


# ------------------------------------------------------------------------------------------------------------
# roundabouts


def test_roundabout_world_has_an_island_the_ego_drives_round() -> None:
    cfg = _only("residential", "street.roundabout_prob=1", "street.main_street_prob=0")
    seq = build_sequence(1, 0, 30, hdl64(), cfg)
    net = seq.world.network
    assert net.roundabouts
    near = [n for n in net.roundabouts if np.min(np.linalg.norm(seq.ego.route_lattice - net.node(*n), axis=1)) < 12]
    assert near, "the route crosses a roundabout"
    for node in near:
        radius = net.roundabouts[node]
        gap = np.min(np.linalg.norm(seq.ego.route_lattice - net.node(*node), axis=1))
        assert gap > radius + 1.0
        ring = net.node(*node) + 0.6 * radius * np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
        labels = _surface_labels(seq, ring)
        assert np.isin(labels, [RAW["terrain"], RAW["vegetation"], RAW["trunk"]]).all(), labels
