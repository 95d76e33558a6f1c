"""The static world around the ego route (u4d_aug/data/sim/world.py): block rectangles by hand, the blocks near the
route, the world built block by block, sidewalk bicycles on request."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.data.sensors import hdl64
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import RAW
from u4d_aug.data.sim.streets import Bend, Line, Network, Warp
from u4d_aug.data.sim.world import World, block_rects, block_sides, build_world, included_blocks
from u4d_aug.data.sim.writer import build_sequence

TINY = REPO / "configs" / "sim" / "tiny.yaml"
ROUTE = np.column_stack([np.linspace(10.0, 50.0, 81), np.full(81, 100.0)])  # along the street y = 100


def _tiny(*overrides: str) -> SimConfig:
    return load_config(SimConfig, TINY, overrides)


def _instances(mesh, label: str) -> int:
    return len(np.unique(mesh.instance[mesh.semantic == RAW[label]]))


def street(position: float) -> Line:
    """One lane per direction (3.5 m), a 2 m parking strip on the negative side, sidewalks 3 m and 4 m."""
    return Line(position, 3.5, 1, (2.0, 0.0), (3.0, 4.0), (0.0, 0.0), False, False)


def straight_network() -> Network:
    """Streets x = 0, 60, 150 and y = 0, 100, 220, unbent and flat."""
    straight = Bend(np.zeros(0), np.zeros(0), np.zeros(0))
    xs, ys = [street(x) for x in (0.0, 60.0, 150.0)], [street(y) for y in (0.0, 100.0, 220.0)]
    return Network(xs, ys, corner_radius=4.0, curb_height=0.12, warp=Warp(straight, straight))


@pytest.fixture(scope="module")
def world() -> World:
    return build_world(np.random.default_rng(0), _tiny("view_radius=5"), straight_network(), ROUTE)


def test_block_sides_and_rectangles_by_hand():
    net = straight_network()
    assert block_sides(net, 1, 0) == [(net.ys[0], 1), (net.xs[2], 0), (net.ys[1], 0), (net.xs[1], 1)]
    curb, inner, sidewalks = block_rects(net, 0, 0)
    # x: 0 + 3.5 (lanes) .. 60 - 3.5 - 2.0 (lanes, parking on the street's negative side); y likewise
    assert curb == (3.5, 3.5, 54.5, 94.5) and sidewalks == [4.0, 3.0, 3.0, 4.0]
    assert inner == (7.5, 7.5, 51.5, 91.5)


def test_blocks_near_the_route_are_included():
    net = straight_network()
    assert included_blocks(net, ROUTE, 5.0) == [(0, 0), (0, 1)]  # x 10-50 along y = 100: the blocks either side
    assert included_blocks(net, ROUTE, 12.0) == [(0, 0), (0, 1), (1, 0), (1, 1)]  # the next ones from 10 m on


def test_the_world_is_built_block_by_block_around_the_route(world):
    net = world.network
    assert [b.index for b in world.blocks] == [(0, 0), (0, 1)]
    for block in world.blocks:
        assert (block.curb, block.inner) == block_rects(net, *block.index)[:2]
        x, y = block.walk_loop.T  # on the sidewalk: inside the curb, outside the lots, counter-clockwise
        x0, y0, x1, y1 = block.curb
        assert x.min() > x0 and x.max() < x1 and y.min() > y0 and y.max() < y1
        i0, j0, i1, j1 = block.inner
        assert not np.any((x > i0) & (x < i1) & (y > j0) & (y < j1))
        assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0
    present = set(np.unique(world.mesh.semantic).tolist())
    assert {RAW[name] for name in ("road", "sidewalk", "building", "vegetation", "pole")} <= present
    assert world.next_instance == int(world.mesh.instance.max()) + 1  # the agents' ids start after the objects'


def test_sidewalk_bicycles_only_when_asked() -> None:
    off = build_sequence(4, 0, 3, hdl64(), _tiny()).world.mesh
    on = build_sequence(4, 0, 3, hdl64(), _tiny("objects.sidewalk_bicycle_prob=1.0")).world.mesh
    assert _instances(on, "bicycle") >= _instances(off, "bicycle") + 10
    # every bicycle is a rigid ~1.8 m object standing on the ground, not floating or buried
    for inst in np.unique(on.instance[on.semantic == RAW["bicycle"]]):
        v = on.vertices[np.unique(on.triangles[(on.instance == inst) & (on.semantic == RAW["bicycle"])])]
        assert 1.3 < np.ptp(v[:, :2], axis=0).max() < 2.2 and 0.8 < np.ptp(v[:, 2]) < 1.4
