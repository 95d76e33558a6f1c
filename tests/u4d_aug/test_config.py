"""Typed configs: defaults <- yaml <- key=value; unknown keys and wrong types are rejected by name."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

import pytest
import yaml

from u4d_aug.config import (
    closest_keys,
    config_from_dict,
    config_keys,
    config_to_dict,
    load_config,
    parse_override,
    save_config,
    saved_config,
    without_removed_keys,
)
from u4d_aug.errors import InputError


@dataclass
class Inner:
    steps: int = 10
    lr: float = 1e-3
    mode: Literal["ddpm", "ddim"] = "ddpm"


@dataclass
class Outer:
    name: str = "run"
    sizes: tuple[int, int] = (64, 1024)
    widths: list[int] = field(default_factory=lambda: [32, 64])
    seed: int | None = None
    inner: Inner = field(default_factory=Inner)


def test_defaults_yaml_then_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: a\ninner:\n  steps: 5\n  lr: 1\n")
    cfg = load_config(Outer, path, ["inner.steps=7", "sizes=[32, 512]", "seed=3"])
    assert cfg.name == "a"
    assert cfg.inner.steps == 7
    assert cfg.inner.lr == 1.0 and isinstance(cfg.inner.lr, float)
    assert cfg.sizes == (32, 512)
    assert cfg.seed == 3
    assert cfg.widths == [32, 64]


def test_float_in_exponent_form_without_dot(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("inner:\n  lr: 1e-4\n")  # yaml 1.1 reads this as the string '1e-4'
    assert load_config(Outer, path).inner.lr == 1e-4
    assert load_config(Outer, None, ["inner.lr=5E+2"]).inner.lr == 500.0
    with pytest.raises(InputError, match="inner.steps"):
        load_config(Outer, None, ["inner.steps=1e3"])  # ints stay strict


def test_unknown_key_is_named_with_valid_keys(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("inner:\n  stepz: 5\n")
    with pytest.raises(
        InputError,
        match=r"unknown config key 'inner.stepz' \(did you mean 'inner.steps'\?\); valid keys here: lr, mode, steps",
    ):
        load_config(Outer, path)


@pytest.mark.parametrize(
    ("override", "hint"),
    [("inner.lrr=1", "'inner.lr'"), ("lr=1", "'inner.lr'"), ("stpes=1", "'inner.steps'"), ("nam=x", "'name'"),
     ("sizez=[1, 2]", "'sizes'")],
)  # fmt: skip
def test_an_unknown_key_names_the_nearest_ones(override, hint):
    with pytest.raises(InputError, match=f"unknown config key '{override.split('=')[0]}' \\(did you mean {hint}\\?\\)"):
        load_config(Outer, None, [override])


def test_a_key_near_none_gets_no_hint_and_nested_keys_are_candidates():
    with pytest.raises(InputError) as error:
        load_config(Outer, None, ["completely_else=1"])
    message = str(error.value)
    assert "did you mean" not in message and "valid keys here: inner, name, seed, sizes, widths" in message
    assert config_keys(Outer) == ["name", "sizes", "widths", "seed", "inner", "inner.steps", "inner.lr", "inner.mode"]
    assert closest_keys(Inner, "inner.mdoe", "inner.") == ["inner.mode"]


@dataclass
class Pruned:
    steps: int = 10

    REMOVED_KEYS: ClassVar[dict] = {"views": (1, "measured no gain")}


@dataclass
class PrunedOuter:
    inner: Pruned = field(default_factory=Pruned)
    REMOVED_KEYS: ClassVar[dict] = {"restart": (0, "changed nothing")}


def test_a_removed_key_is_named_as_removed_and_a_saved_config_still_reads():
    with pytest.raises(InputError, match=r"config key 'inner.views' was removed \(measured no gain\); delete it"):
        load_config(PrunedOuter, None, ["inner.views=4"])
    with pytest.raises(InputError, match="unknown config key 'inner.viewz'"):
        load_config(PrunedOuter, None, ["inner.viewz=4"])
    saved = {"restart": 0, "inner": {"steps": 3, "views": 1}}  # written before the keys were removed, both "off"
    assert without_removed_keys(PrunedOuter, saved) == ({"inner": {"steps": 3}}, {})
    assert saved_config(PrunedOuter, saved, "old.pt") == PrunedOuter(Pruned(3))
    saved["inner"]["views"] = 4  # a removed setting that acted: named, then read without it
    assert without_removed_keys(PrunedOuter, saved)[1] == {"inner.views": 4}
    with pytest.warns(UserWarning, match="old.pt: trained with inner.views=4, a setting since removed"):
        assert saved_config(PrunedOuter, saved, "old.pt") == PrunedOuter(Pruned(3))


def test_wrong_type_in_yaml_is_named(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("inner:\n  steps: many\n")
    with pytest.raises(InputError, match=r"c.yaml: key 'inner.steps' expects int, got 'many'"):
        load_config(Outer, path)


def test_literal_lists_allowed_values():
    with pytest.raises(InputError, match=r"'inner.mode' must be one of 'ddpm', 'ddim'"):
        load_config(Outer, None, ["inner.mode=euler"])


def test_bad_yaml_and_missing_file(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("a: [1, 2\n")
    with pytest.raises(InputError, match="not valid yaml"):
        load_config(Outer, path)
    with pytest.raises(InputError, match="config file not found"):
        load_config(Outer, tmp_path / "nope.yaml")
    with pytest.raises(InputError, match="expected key=value"):
        parse_override("inner.steps")


def test_resolved_config_round_trips(tmp_path):
    cfg = load_config(Outer, None, ["inner.mode=ddim", "widths=[1, 2, 3]"])
    save_config(cfg, tmp_path / "resolved.yaml")
    data = yaml.safe_load((tmp_path / "resolved.yaml").read_text())
    assert data == config_to_dict(cfg)
    assert config_from_dict(Outer, data) == cfg
