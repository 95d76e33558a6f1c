"""Typed configuration of the simulated world (u4d_aug/data/sim/config.py): defaults, what the presets change, the
measured sensor terms off by default, refusals that name the key."""

from __future__ import annotations

import dataclasses
import re

import pytest

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.data.sim.config import LidarConfig, SimConfig
from u4d_aug.errors import InputError


def flat(cfg: SimConfig) -> dict[str, object]:
    """dotted key -> value of a resolved config."""
    return {
        f"{section}.{key}" if isinstance(values, dict) else section: value
        for section, values in dataclasses.asdict(cfg).items()
        for key, value in (values.items() if isinstance(values, dict) else [(None, values)])
    }


def test_the_tiny_preset_changes_only_the_keys_it_names():
    default, tiny = flat(SimConfig()), flat(load_config(SimConfig, REPO / "configs" / "sim" / "tiny.yaml", []))
    assert flat(load_config(SimConfig, None, [])) == default
    changed = {key: tiny[key] for key in default if tiny[key] != default[key]}
    assert changed == {
        "view_radius": 60.0,
        "lidar.azimuth_steps": 360,
        "agents.cars_per_100m": 4.0,
        "agents.pedestrians_per_100m": 6.0,
    }


def test_new_terms_off_by_default() -> None:
    cfg = LidarConfig()
    assert cfg.surface_model == "basic" and cfg.mixed_pixel_prob == 0 and cfg.dark_drop == 0
    assert cfg.ring_gain_spread == 0 and cfg.speckle == 0 and cfg.range_noise_per_m == 0
    varied = load_config(SimConfig, "sim/varied", []).lidar
    assert varied.surface_model == "measured" and dataclasses.asdict(varied) != dataclasses.asdict(cfg)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["view_radius=0"], "'view_radius' must be > 0"),
        (["frame_rate=.nan"], "frame_rate"),
        (["lidar.dark_drop=-0.1"], "'lidar.dark_drop' must be >= 0"),
        (["lots.park_block_prob=0.6", "lots.plaza_block_prob=0.5"], "'lots.park/plaza/parking_block_prob' must sum"),
        (["street.main_lanes=[3, 2]"], "key 'street.main_lanes' must be (low, high) with 1 <= low <= high"),
    ],
)
def test_bad_values_are_refused_naming_the_key(overrides, message):
    with pytest.raises(InputError, match=re.escape(message)):
        load_config(SimConfig, None, overrides)
