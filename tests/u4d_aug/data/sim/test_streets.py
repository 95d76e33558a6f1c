"""Street network of the simulated world (u4d_aug/data/sim/streets.py): bends and hills within their limits, lane
paths round a roundabout, arc length along a path."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.streets import DIRECTIONS, Line, arc_length, lane_path, make_hills, make_network, sample_path

TINY = REPO / "configs" / "sim" / "tiny.yaml"


def _tiny(*overrides: str) -> SimConfig:
    return load_config(SimConfig, TINY, overrides)


def test_streets_bend_within_limits() -> None:
    cfg = _tiny("street.straight_prob=0")
    warp = make_network(np.random.default_rng(3), cfg.street, 400.0).warp
    s = np.linspace(-400.0, 400.0, 8001)
    for bend in (warp.bend_x, warp.bend_y):
        slope = bend.slope(s)
        np.testing.assert_allclose(np.gradient(bend(s), s), slope, atol=1e-3)
        assert np.ptp(np.degrees(np.arctan(slope))) > 10.0  # the streets genuinely change direction
        assert np.abs(slope).max() <= cfg.street.bend_max_slope + 1e-9
        curvature = np.abs(np.gradient(slope, s)) / (1.0 + slope**2) ** 1.5
        assert curvature.max() <= 1.0 / cfg.street.bend_min_radius + 1e-4
    straight = make_network(np.random.default_rng(3), _tiny("street.straight_prob=1").street, 400.0).warp
    xy = np.random.default_rng(0).uniform(-300, 300, (100, 2))
    np.testing.assert_array_equal(straight.points(xy), xy)


def test_hills_gradient_and_limits() -> None:
    cfg = _tiny("street.flat_prob=0")
    xy = np.random.default_rng(0).uniform(-400, 400, (2000, 2))
    for seed in range(5):
        hills = make_hills(np.random.default_rng(seed), cfg.street)
        eps = 1e-3
        numeric = np.stack(
            [
                (hills(xy + [eps, 0]) - hills(xy - [eps, 0])) / (2 * eps),
                (hills(xy + [0, eps]) - hills(xy - [0, eps])) / (2 * eps),
            ],
            axis=-1,
        )
        np.testing.assert_allclose(hills.gradient(xy), numeric, atol=1e-6)
        grade = np.linalg.norm(hills.gradient(xy), axis=1)
        assert grade.max() <= cfg.street.hill_max_grade + 1e-9
        assert np.ptp(hills(xy)) > 1.0  # genuinely hilly over a few hundred metres
        assert np.sum(np.abs(hills.amplitude) * np.linalg.norm(hills.wavevector, axis=1) ** 2) <= (
            1.0 / cfg.street.hill_min_radius + 1e-12
        )
    flat = make_hills(np.random.default_rng(0), _tiny("street.flat_prob=1").street)
    assert np.all(flat(xy) == 0.0)


def _roundabout_net(island: float = 4.0):
    cfg = load_config(SimConfig, None, ["street.main_street_prob=0"]).street
    net = make_network(np.random.default_rng(0), cfg, 300.0)
    i, j = len(net.xs) // 2, len(net.ys) // 2
    net.roundabouts[(i, j)] = island
    return net, (i, j)


@pytest.mark.parametrize("turn, sweep_deg", [(0, (120, 200)), (3, (40, 110)), (1, (220, 300))])
def test_roundabout_paths_circle_the_island(turn: int, sweep_deg) -> None:
    net, (i, j) = _roundabout_net()
    out = DIRECTIONS[turn].astype(int)  # along +x into the roundabout, then straight (0), right (3) or left (1)
    nodes = [(i - 1, j), (i, j), (i + out[0], j + out[1])]
    path, turning = lane_path(net, nodes, lambda line, side: line.lane_width / 2)
    center = net.node(i, j)
    dist = np.linalg.norm(path - center, axis=1)
    assert dist.min() >= net.roundabouts[(i, j)] + 1.0  # never over the island
    assert np.all(np.linalg.norm(np.diff(path, axis=0), axis=1) < 0.2)  # one continuous path
    arc = path[turning > 0]
    angles = np.unwrap(np.arctan2(*(arc - center).T[::-1]))
    swept = np.degrees(angles[-1] - angles[0])
    assert sweep_deg[0] < swept < sweep_deg[1]  # counter-clockwise, as right-hand traffic goes round


def test_a_street_cross_section_adds_up():
    line = Line(0.0, 3.5, 2, (2.5, 0.0), (3.0, 4.0), (0.0, 1.5), True, True)
    assert line.half_road == 7.0 and line.curb(0) == 9.5 and line.curb(1) == 7.0


def test_arc_length_and_positions_headings_along_a_path():
    path = np.array([(0.0, 0.0), (3.0, 4.0), (3.0, 10.0)])  # 5 m up and to the right, then 6 m along +y
    s = arc_length(path)
    np.testing.assert_allclose(s, [0.0, 5.0, 11.0])
    xy, heading = sample_path(path, s, np.array([-1.0, 2.5, 8.0, 20.0]))
    np.testing.assert_allclose(xy, [(0.0, 0.0), (1.5, 2.0), (3.0, 7.0), (3.0, 10.0)])  # clipped at both ends
    np.testing.assert_allclose(heading[1:3], [np.arctan2(4.0, 3.0), np.pi / 2])
