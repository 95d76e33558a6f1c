"""SamplingSettings: its defaults are the shipped preset's, `u4d generate` builds the same from its keys, bad values
are one-line errors naming the field."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig
from u4d_aug.sampling_settings import DEFAULT_SAMPLING, SamplingSettings

PRESET = REPO / "configs" / "u4d" / "generate_hdl64.yaml"
# SamplingSettings field -> `u4d generate` key
KEYS = {"sampler": "sampler", "grid": "sampler_grid", "steps": "steps", "stage1_steps": "stage1_steps",
        "stage1_mask_fraction": "stage1_mask_fraction", "mean_start_below": "mean_start_below"}  # fmt: skip


def test_the_defaults_are_the_shipped_preset_s():
    preset = yaml.safe_load(PRESET.read_text(encoding="utf-8"))
    assert SamplingSettings(**{field: preset[key] for field, key in KEYS.items()}) == SamplingSettings()
    assert SamplingSettings() == DEFAULT_SAMPLING
    assert SamplingSettings() == SamplingSettings("dpmpp2m-sde", "time", 20, 6, 0.1, -10.0)  # the golden values
    assert load_config(GenerateConfig, PRESET).sampling() == SamplingSettings()


def test_a_default_generate_config_samples_with_the_default_settings():
    assert GenerateConfig().sampling() == SamplingSettings()
    assert [field.name for field in dataclasses.fields(SamplingSettings)] == list(KEYS)  # a new field needs its key
    cfg = load_config(GenerateConfig, None, ["sampler=ddpm", "steps=7", "stage1_steps=null", "mean_start_below=null"])
    assert cfg.sampling() == SamplingSettings(sampler="ddpm", steps=7, stage1_steps=None, mean_start_below=None)


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"sampler": "euler"}, "sampler"),
        ({"sampler": "ddpm", "grid": "logsnr"}, "grid"),
        ({"grid": "karras"}, "grid"),
        ({"steps": 0}, "steps"),
        ({"steps": 2.5}, "steps"),
        ({"steps": True}, "steps"),
        ({"stage1_steps": 0}, "stage1_steps"),
        ({"stage1_mask_fraction": 0.0}, "stage1_mask_fraction"),
        ({"stage1_mask_fraction": 1.5}, "stage1_mask_fraction"),
        ({"mean_start_below": float("nan")}, "mean_start_below"),
        ({"mean_start_below": "-10"}, "mean_start_below"),
    ],
)
def test_bad_settings_are_input_errors_naming_the_field(options, field):
    with pytest.raises(InputError, match=f"^{field}: ") as caught:
        SamplingSettings(**options)
    assert "\n" not in str(caught.value)


def test_settings_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        SamplingSettings().steps = 3  # type: ignore[misc]
