"""Every shipped yaml under configs/ loads into its dataclass: a typo in a preset fails here, not mid-run."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from segmentation.config import SegTrainConfig
from segmentation.experiment import ExperimentConfig, run_config
from tests.tiny_nets import REPO
from u4d_aug.autoencoder_stage import AutoencoderTrainConfig
from u4d_aug.config import load_config
from u4d_aug.data.sensors import get_sensor
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.generate import GenerateConfig
from u4d_aug.metrics.extractors import ExtractorConfig
from u4d_aug.train import DiffusionTrainConfig

CONFIGS = REPO / "configs"
RECORDED = REPO / "benchmarks" / "experiments"  # the experiment configs behind recorded results
PRESETS = sorted(CONFIGS.glob("*/*.yaml")) + sorted(RECORDED.glob("*.yaml"))


def config_class(path: Path) -> type:
    """The dataclass a preset is read with, from its folder (and name, for configs/u4d/generate_*)."""
    folder = path.parent.name
    if folder == "seg":
        return SegTrainConfig
    elif folder in ("experiment", "experiments"):
        return ExperimentConfig
    elif folder == "sim":
        return SimConfig
    elif folder == "extractor":
        return ExtractorConfig
    elif folder == "u4d":
        if path.stem.startswith("autoencoder"):
            return AutoencoderTrainConfig
        return GenerateConfig if path.stem.startswith("generate") else DiffusionTrainConfig
    raise AssertionError(f"{path}: no config class known for folder {folder!r}; add it to config_class")


def test_presets_are_found():
    assert {p.parent.name for p in PRESETS} >= {"seg", "experiment", "sim", "extractor", "u4d", "sensors"}


@pytest.mark.parametrize("path", PRESETS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_preset_loads(path: Path):
    if path.parent.name == "sensors":
        sensor = get_sensor(path)
        assert sensor.height == len(sensor.elevations_deg)
        return
    cfg = load_config(config_class(path), path)
    if isinstance(cfg, ExperimentConfig):  # every run of the experiment resolves (base + overrides + arm)
        for arm in cfg.arms:
            for backbone in cfg.backbones:
                run = run_config(cfg, arm, backbone, cfg.seeds[0])
                assert run.mode == arm.mode and run.model.name == backbone


def test_fewlabel_fit_changes_only_lr_and_loss_level():
    """cpu_fewlabel_fit is cpu_fewlabel with optim.lr=0.01 and loss.level=voxel, nothing else."""
    base = load_config(ExperimentConfig, RECORDED / "cpu_fewlabel.yaml")
    fit = load_config(ExperimentConfig, RECORDED / "cpu_fewlabel_fit.yaml")
    for arm_base, arm_fit in zip(base.arms, fit.arms):
        a, b = run_config(base, arm_base, "minkunet", 0), run_config(fit, arm_fit, "minkunet", 0)
        assert (b.optim.lr, b.loss.level) == (0.01, "voxel")
        b.optim.lr, b.loss.level, b.out_dir = a.optim.lr, a.loss.level, a.out_dir
        assert a == b


def recorded_overrides(results_json: str) -> list[str]:
    """The key=value overrides of the training command a results json records (not threads, seed, env)."""
    path = CONFIGS.parent / "benchmarks" / "results" / "segmentation" / "seg_cpu_rich" / results_json
    words = shlex.split(json.loads(path.read_text())["command"])
    return [w for w in words if "=" in w and not w.startswith(("threads=", "seed=", "OMP_NUM_THREADS="))]


def test_supervised_cpu_preset_is_the_measured_recipe():
    """configs/seg/cpu_minkunet.yaml is what its results jsons measured. The last runs (a faster host) trained it
    as it is. The runs before trained it with model.readout=voxel and were evaluated with both readouts (the
    voxel-level losses do not read the readout, so the preset trains the same net) and with optim.steps=2400: on
    that host the 30-minute budget ended the cosine after ~950 steps, so the step cap never bound. The recipe
    before them (six overrides of the first preset) is it too."""
    preset = CONFIGS / "seg" / "cpu_minkunet.yaml"
    current = load_config(SegTrainConfig, preset)
    assert load_config(SegTrainConfig, preset, recorded_overrides("zen5_seeds.json")) == current
    measured = load_config(SegTrainConfig, preset, recorded_overrides("keep_gathers_seeds.json"))
    assert (measured.model.readout, current.model.readout, current.loss.level) == ("voxel", "trilinear", "voxel")
    measured.model.readout = "trilinear"
    measured.optim.steps = 2400
    earlier = recorded_overrides("local_features_seeds.json")
    assert len(earlier) >= 6  # decoder channels and blocks, voxel size, lr, steps, input features
    assert load_config(SegTrainConfig, preset, earlier) == measured
    measured.optim.steps = current.optim.steps
    assert measured == current
