"""Street types of the simulated world: each place (sequence) draws one, which sets its layout of ground classes.

The defaults (`residential` only) are the SemanticKITTI seq-00 layout the world was tuned to, and stay bit for bit.
Other types change the place's SimConfig before anything is built (pure function `street_type_config`): the street
cross-section (lanes, medians, lawn strips, kerb height, sidewalk material), what fills the blocks (houses, row
houses, parks, squares, parking lots, driveways), street furniture and the agents' densities; a key the world's
config sets away from its default keeps that value in every type (so `lots.driveway_prob=1` holds everywhere).
configs/sim/varied.yaml mixes them (`street_types.<name>: weight`). The type of place k comes from
np.random.default_rng([seed, k, 0, 5]), a stream of its own, so it changes nothing else of the place.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from u4d_aug.data.sim.config import SimConfig, StreetTypeWeights
from u4d_aug.errors import InputError

STREET_TYPES = tuple(f.name for f in dataclasses.fields(StreetTypeWeights))


def type_weights(weights: StreetTypeWeights) -> np.ndarray:
    """(len(STREET_TYPES),) normalised weights in STREET_TYPES order."""
    w = np.array([getattr(weights, name) for name in STREET_TYPES], dtype=np.float64)
    return w / w.sum()


def place_street_type(seed: int, index: int, weights: StreetTypeWeights) -> str:
    """Street type of place `index`: drawn from its own stream; no draw when one type has all the weight."""
    w = type_weights(weights)
    if np.count_nonzero(w) == 1:
        return STREET_TYPES[int(np.flatnonzero(w)[0])]
    rng = np.random.default_rng([seed, index, 0, 5])
    return STREET_TYPES[int(rng.choice(len(STREET_TYPES), p=w))]


def _replace(cfg: SimConfig, section: str, **changes) -> SimConfig:
    """`cfg` with the type's `changes` of one section, except keys the world's config sets away from the default."""
    current = getattr(cfg, section)
    default = type(current)()
    kept = {k: v for k, v in changes.items() if getattr(current, k) == getattr(default, k)}
    return dataclasses.replace(cfg, **{section: dataclasses.replace(current, **kept)})


def street_type_config(cfg: SimConfig, kind: str) -> SimConfig:
    """The place's config: `cfg` changed as street type `kind` lays out a street (residential: `cfg` itself)."""
    if kind == "residential":
        return cfg
    elif kind == "arterial":
        return _arterial(cfg)
    elif kind == "intersection":
        return _intersection(cfg)
    elif kind == "park":
        return _park(cfg)
    elif kind == "parking":
        return _parking(cfg)
    elif kind == "green":
        return _green(cfg)
    elif kind == "plaza":
        return _plaza(cfg)
    raise InputError(f"street type {kind!r}: expected one of {', '.join(STREET_TYPES)}")


def _arterial(cfg: SimConfig) -> SimConfig:
    """Wide multi-lane roads (2-3 lanes per direction, 3.3-3.7 m), lawn or paved medians, broad sidewalks in
    concrete, kerbs up to 20 cm, row houses and shops, more and faster traffic."""
    cfg = _replace(
        cfg,
        "street",
        main_street_prob=0.75,
        main_lanes=(2, 3),
        lane_width=(3.3, 3.7),
        median_prob=0.6,
        median_terrain_prob=0.5,
        sidewalk_width=(3.5, 6.0),
        grass_strip_prob=0.3,
        curb_height=(0.14, 0.20),
        crosswalk_prob=0.7,
        parking_prob=0.2,
        block_size=(80.0, 160.0),
        sidewalk_material="concrete",
        signal_prob=0.6,
    )
    cfg = _replace(cfg, "lots", kind_weights=(0.15, 0.35, 0.05, 0.15, 0.30), row_floors=(4, 7))
    cfg = _replace(cfg, "objects", pole_spacing=(18.0, 28.0), sign_prob=1.0, object_prob=0.6)
    return _replace(
        cfg,
        "agents",
        cars_per_100m=5.0,
        trucks_per_100m=0.5,
        vans_per_100m=0.5,
        pedestrians_per_100m=4.0,
        bicyclists_per_100m=1.5,
        motorcyclists_per_100m=1.0,
        ego_speed=(7.0, 13.0),
        agent_route_extra=300.0,
    )


def _intersection(cfg: SimConfig) -> SimConfig:
    """Short blocks, so the route crosses (and turns at) a junction every 45-80 m: crosswalks, traffic lights,
    roundabouts where two residential streets meet."""
    cfg = _replace(
        cfg,
        "street",
        block_size=(45.0, 80.0),
        main_street_prob=0.4,
        crosswalk_prob=1.0,
        corner_radius=(5.0, 10.0),
        signal_prob=0.8,
        sidewalk_width=(3.0, 5.0),
        roundabout_prob=0.3,
    )
    cfg = _replace(cfg, "lots", kind_weights=(0.25, 0.45, 0.05, 0.05, 0.20))  # town centre: row houses
    cfg = _replace(cfg, "objects", sign_prob=1.0)
    return _replace(
        cfg, "agents", ego_turn_prob=0.7, cars_per_100m=3.5, pedestrians_per_100m=5.0, bicyclists_per_100m=1.5
    )


def _park(cfg: SimConfig) -> SimConfig:
    """Park-side road: a 1.5-3 m lawn strip with street trees between the kerb and the paving, parks behind."""
    cfg = _replace(
        cfg,
        "street",
        grass_strip_prob=0.9,
        grass_width=(1.5, 3.0),
        sidewalk_width=(3.5, 6.0),
        curb_height=(0.08, 0.14),
        parking_prob=0.35,
    )
    cfg = _replace(cfg, "lots", park_block_prob=0.3, kind_weights=(0.50, 0.10, 0.30, 0.03, 0.07))
    cfg = _replace(cfg, "objects", street_tree_prob=0.95, tree_spacing=(6.0, 10.0), sidewalk_bicycle_prob=0.1)
    return _replace(cfg, "agents", pedestrians_per_100m=5.0, bicyclists_per_100m=2.0, standing_person_prob=0.3)


def _parking(cfg: SimConfig) -> SimConfig:
    """Parking lots (hedged), driveways to the houses, dropped kerbs (4-10 cm), marked parking strips."""
    cfg = _replace(cfg, "street", curb_height=(0.04, 0.10), parking_prob=0.35, parking_label_prob=0.9)
    cfg = _replace(
        cfg,
        "lots",
        parking_block_prob=0.3,
        driveway_prob=0.7,
        kind_weights=(0.30, 0.05, 0.05, 0.30, 0.30),
    )
    cfg = _replace(cfg, "objects", parked_occupancy=(0.3, 0.7), bicycle_prob=0.6)
    return _replace(cfg, "agents", cars_per_100m=3.0, pedestrians_per_100m=3.0, standing_person_prob=0.3)


def _green(cfg: SimConfig) -> SimConfig:
    """Dense vegetation: tall hedges, gardens, close street trees, shrub-covered yards, big courtyard trees."""
    cfg = _replace(cfg, "street", grass_strip_prob=0.4, grass_width=(1.2, 2.5), sidewalk_width=(3.0, 5.0))
    cfg = _replace(
        cfg,
        "lots",
        kind_weights=(0.45, 0.03, 0.45, 0.02, 0.05),
        hedge_prob=1.0,
        hedge_height=(1.2, 2.5),
        yard_trees=(4, 8),
        yard_bushes=(8, 16),
        ground_cover_prob=0.9,
        courtyard_tree_area=60.0,
    )
    return _replace(cfg, "objects", street_tree_prob=1.0, tree_spacing=(5.0, 8.0))


def _plaza(cfg: SimConfig) -> SimConfig:
    """Small squares: cobbled blocks with planters, benches and kiosks; low kerbs, people standing and walking."""
    cfg = _replace(cfg, "street", sidewalk_width=(4.0, 8.0), curb_height=(0.03, 0.08), sidewalk_material="cobble")
    cfg = _replace(cfg, "lots", plaza_block_prob=0.3, kind_weights=(0.10, 0.45, 0.05, 0.05, 0.35))
    cfg = _replace(cfg, "objects", object_prob=0.9, sidewalk_bicycle_prob=0.3, bicycle_prob=0.7)
    return _replace(cfg, "agents", pedestrians_per_100m=10.0, standing_person_prob=0.4, bicyclists_per_100m=2.0)
