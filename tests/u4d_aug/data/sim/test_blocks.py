"""Blocks of another use than building lots (u4d_aug/data/sim/blocks.py): the draw of a block's use, and a park, a
square and a parking lot built into an empty block: their classes, where they lie, the walks they return."""

from __future__ import annotations

import numpy as np
import pytest

from u4d_aug.data.sim import blocks
from u4d_aug.data.sim.config import LotConfig, SimConfig
from u4d_aug.data.sim.geometry import RAW, MeshBuilder
from u4d_aug.data.sim.world import _Ids

INNER = (0.0, 0.0, 48.0, 36.0)  # the block's lot rectangle, lattice coordinates
H = 0.15  # sidewalk height


def flat(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ground without undulation."""
    return np.zeros(np.broadcast(x, y).shape)


def labels_of(mesh) -> set[str]:
    return {name for name, raw in RAW.items() if raw in set(mesh.semantic.tolist())}


def inside(points: np.ndarray, rect) -> bool:
    x0, y0, x1, y1 = rect
    return bool(np.all((points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)))


def test_block_use_draws_nothing_when_every_use_is_off():
    rng = np.random.default_rng(0)
    assert blocks.block_use(rng, LotConfig()) == "lots"
    assert rng.random() == np.random.default_rng(0).random()  # the default world keeps its random numbers
    assert blocks.block_use(rng, LotConfig(park_block_prob=1.0)) == "park"
    mixed = LotConfig(park_block_prob=0.2, plaza_block_prob=0.3, parking_block_prob=0.1)
    drawn = [blocks.block_use(rng, mixed) for _ in range(4000)]
    shares = {use: drawn.count(use) / 4000 for use in blocks.BLOCK_USES}
    for use, expected in (("lots", 0.4), ("park", 0.2), ("plaza", 0.3), ("parking", 0.1)):
        assert shares[use] == pytest.approx(expected, abs=0.03), (use, shares)


def test_a_park_is_a_lawn_crossed_by_two_paths():
    mb = MeshBuilder()
    walks = blocks.park(mb, np.random.default_rng(1), SimConfig(), INNER, H, flat)
    park = mb.build()
    assert {"terrain", "vegetation", "trunk", "pole"} <= labels_of(park)
    assert labels_of(park) & {"sidewalk", "other-ground"}  # paved or gravel paths
    lawn = np.unique(park.triangles[park.semantic == RAW["terrain"]])
    np.testing.assert_allclose(park.vertices[lawn, 2], H + 0.05, atol=1e-6)  # lawn on the flat ground
    along_x, along_y = walks
    np.testing.assert_allclose(along_x[:, 0], [0.0, 48.0])
    np.testing.assert_allclose(along_y[:, 1], [0.0, 36.0])
    assert along_x[0, 1] == along_x[1, 1] and along_y[0, 0] == along_y[1, 0]  # straight across the block
    small = MeshBuilder()
    assert blocks.park(small, np.random.default_rng(1), SimConfig(), (0.0, 0.0, 10.0, 36.0), H, flat) == []
    assert small.build().num_triangles == 0  # too narrow for a park: nothing built


def test_a_square_is_paved_with_walks_inside_it():
    cfg = SimConfig()
    mb = MeshBuilder()
    walks = blocks.plaza(mb, np.random.default_rng(2), cfg, INNER, H, _Ids())
    square = mb.build()
    assert {"sidewalk", "terrain", "vegetation", "pole"} <= labels_of(square)
    paving = square.semantic == RAW["sidewalk"]
    xy = square.vertices[np.unique(square.triangles[paving]), :2]
    assert xy[:, 0].min() == 0.0 and xy[:, 0].max() == 48.0 and xy[:, 1].max() == 36.0  # the whole block
    assert len(walks) == 2 and all(len(walk) == 4 and inside(walk, INNER) for walk in walks)


def test_a_parking_lot_holds_rows_of_vehicles_each_its_own_instance():
    ids = _Ids()
    mb = MeshBuilder()
    walks = blocks.parking_lot(mb, np.random.default_rng(3), SimConfig(), INNER, H, ids)
    lot = mb.build()
    assert {"parking", "car", "terrain", "sidewalk"} <= labels_of(lot)
    vehicles = np.isin(lot.semantic, [RAW["car"], RAW["other-vehicle"]])
    instances = np.unique(lot.instance[vehicles])
    assert len(instances) >= 4 and instances.tolist() == list(range(1, ids.next))  # one id per vehicle
    for instance in instances:
        body = lot.vertices[np.unique(lot.triangles[lot.instance == instance]), :2]
        assert inside(body, INNER)
    np.testing.assert_allclose(walks[0], [(1.0, 1.0), (47.0, 1.0), (47.0, 35.0), (1.0, 35.0)])
