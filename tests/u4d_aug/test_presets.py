"""Presets named by their path under configs/ (u4d_aug/presets.py) resolve from any folder; the wheel ships configs/ as
package data."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import tomllib
from setuptools import find_packages

from segmentation.config import SegTrainConfig
from segmentation.experiment import ExperimentConfig, run_config
from tests.tiny_nets import REPO
from u4d_aug.config import load_config, read_yaml
from u4d_aug.data.sensors import get_sensor
from u4d_aug.demo import DEMO_PRESETS, demo_experiment, demo_steps
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig
from u4d_aug.presets import closest_presets, configs_root, list_presets, resolve_config_path
from u4d_aug.train import DiffusionTrainConfig


@pytest.fixture
def elsewhere(tmp_path, monkeypatch) -> Path:
    """An empty working folder outside the repository."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_configs_root_is_the_top_level_folder_of_a_checkout():
    assert configs_root() == REPO / "configs"


@pytest.mark.parametrize("name", ["seg/tiny", "seg/tiny.yaml", "configs/seg/tiny.yaml", "./configs/seg/tiny"])
def test_a_preset_by_name_from_any_folder(elsewhere, name):
    assert resolve_config_path(name) == REPO / "configs" / "seg" / "tiny.yaml"
    assert load_config(SegTrainConfig, name).model.voxel_size == 0.5


def test_a_file_that_exists_wins_over_the_preset(elsewhere):
    own = elsewhere / "configs" / "seg" / "tiny.yaml"
    own.parent.mkdir(parents=True)
    own.write_text("optim:\n  steps: 123\n")
    assert load_config(SegTrainConfig, "configs/seg/tiny.yaml").optim.steps == 123
    assert load_config(SegTrainConfig, "seg/tiny").optim.steps == 6  # not a path here: the preset
    absolute = REPO / "configs" / "u4d" / "cpu_hdl64.yaml"
    assert resolve_config_path(absolute) == absolute


def test_unknown_preset_is_a_one_line_error(elsewhere):
    with pytest.raises(InputError, match="seg/nope: config file not found, nor a preset") as error:
        read_yaml("seg/nope")
    assert "\n" not in str(error.value)


@pytest.mark.parametrize(
    ("name", "hint"),
    [("seg/tny", "'seg/tiny'"), ("configs/seg/tiny_semii.yaml", "'seg/tiny_semi'"), ("sim/seg_ricj", "'sim/seg_rich'")],
)
def test_an_unknown_preset_names_the_nearest_ones(elsewhere, name, hint):
    with pytest.raises(InputError, match=f"config file not found, nor a preset .* \\(did you mean {hint}"):
        read_yaml(name)
    assert closest_presets(name)[0] == hint.strip("'")


def test_a_name_near_no_preset_gets_the_example_instead(elsewhere):
    with pytest.raises(InputError, match=r"nor a preset of that name under .* \(e.g. seg/tiny\)$"):
        read_yaml("nothing/like/it")
    assert closest_presets(elsewhere / "seg" / "tny.yaml") == []  # an absolute path names a file, not a preset


def test_presets_that_name_presets_resolve_from_any_folder(elsewhere):
    """Experiment configs name their seg-train preset (`base: configs/seg/cpu_semi.yaml`)."""
    cfg = load_config(ExperimentConfig, "experiment/downstream_10pct")
    run = run_config(cfg, cfg.arms[0], cfg.backbones[0], cfg.seeds[0])
    assert run.mode == cfg.arms[0].mode
    assert get_sensor("configs/sensors/example_sensor.yaml").height > 0


def test_demo_presets_resolve_outside_the_repository(elsewhere):
    assert load_config(SegTrainConfig, DEMO_PRESETS["seg"]).model.name == "minkunet"
    assert load_config(DiffusionTrainConfig, DEMO_PRESETS["diffusion"], ["diffusion.stage=u4d"]).height > 0
    assert load_config(GenerateConfig, DEMO_PRESETS["generate"]).num > 0
    assert load_config(GenerateConfig, DEMO_PRESETS["generate_toy"]).num > 0
    assert load_config(GenerateConfig, DEMO_PRESETS["generate_4d"]).propagate
    roles = ("u4d", "baseline", "u4d_most_stage1", "u4d_most_stage2")  # the 4D step's nets too
    shipped = {name: elsewhere / f"{name}.pt" for name in roles}
    steps = [*demo_steps(elsewhere / "demo", 0, elsewhere / "no-real", shipped)]
    steps += demo_steps(elsewhere / "demo", 0, elsewhere / "no-real", None)  # no weights/: the seconds-trained nets
    commands = [step.command for step in steps]
    named = [word for command in commands for word in command if word in DEMO_PRESETS.values()]
    named.append(demo_experiment(elsewhere / "demo", 0)["base"])  # the downstream step's config file names it
    assert sorted(set(named)) == sorted(DEMO_PRESETS.values())
    assert load_config(SegTrainConfig, DEMO_PRESETS["experiment_base"]).mode == "semi"
    assert not [word for command in commands for word in command if "configs/" in word]


def test_list_presets_names_every_shipped_yaml():
    presets = list_presets()
    assert {"seg/tiny", "u4d/cpu_hdl64", "experiment/downstream_10pct", "sensors/example_sensor"} <= set(presets)
    assert len(presets) == len(list((REPO / "configs").glob("*/*.yaml")))


def test_pyproject_lists_every_package_and_maps_configs_into_the_wheel():
    """`packages` is listed by hand (for the configs/ mapping): a new package must be added there."""
    setuptools = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = set(find_packages(where=str(REPO), include=["u4d_aug*", "segmentation*"]))
    assert set(setuptools["packages"]) == found | {"u4d_aug.configs"}
    assert setuptools["package-dir"] == {"u4d_aug.configs": "configs"}
    assert setuptools["package-data"]["u4d_aug.configs"] == ["**/*.yaml"]


def build_wheel(tmp_path: Path) -> Path:
    """Build the wheel from a copy of the sources (not in the checkout: setuptools writes build/ beside them)."""
    source = tmp_path / "src"
    files = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard", "pyproject.toml", "README.md", "configs", "u4d_aug",
         "segmentation"],
        cwd=REPO, capture_output=True, text=True, check=True,
    ).stdout.split()  # fmt: skip
    for name in files:
        if (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            (source / name).write_bytes((REPO / name).read_bytes())
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path), "."],
        cwd=source, check=True,
    )  # fmt: skip
    (wheel,) = tmp_path.glob("u4d_aug-*.whl")
    return wheel


@pytest.mark.slow
def test_the_wheel_holds_the_presets(tmp_path):
    names = set(zipfile.ZipFile(build_wheel(tmp_path)).namelist())
    shipped = {
        f"u4d_aug/configs/{p.relative_to(REPO / 'configs').as_posix()}" for p in (REPO / "configs").glob("**/*.yaml")
    }
    assert shipped <= names
    assert "u4d_aug/presets.py" in names and not any(n.startswith("configs/") for n in names)
    assert {"u4d_aug/py.typed", "segmentation/py.typed"} <= names  # PEP 561: type checkers read the inline types


BANK_IN_A_LOADER = """
import numpy as np
from pathlib import Path
from torch.utils.data import DataLoader
from u4d_aug import ScanDataset, collate_scans
import u4d_aug
from u4d_aug.bank import BankLayout, sample_digests, write_manifest, write_sample
assert "site-packages" in u4d_aug.__file__, u4d_aug.__file__  # the installed copy, not the checkout
layout, samples = BankLayout(Path("bank"), 1), []
for i in range(3):  # a bank as `u4d generate` writes it
    points = np.random.default_rng(i).uniform(0, 1, (100 + i, 4)).astype(np.float32)
    write_sample(layout, i, points, mask=np.ones((2, 8), dtype=bool))
    samples.append({"index": i, "seed": i, "sha256": sample_digests(layout, i)})
write_manifest(Path("bank"), {"mode": "u4d", "frames": 1, "samples": samples, "complete": True})
batch = next(iter(DataLoader(ScanDataset(Path("bank")), batch_size=2, collate_fn=collate_scans)))
assert batch["points"].shape == (201, 4) and batch["labels"] is None
assert batch["offsets"].tolist()[0] == 0 and len(batch["offsets"]) == 3 and batch["points"].shape[1] == 4
print("batch", tuple(batch["points"].shape))
"""


@pytest.mark.slow
def test_non_editable_install_runs_from_an_empty_folder(tmp_path):
    """`pip install` of the wheel into a fresh venv (torch and the other dependencies from the system site), then,
    in an empty folder: simulate a tiny world, seg-train two steps of a preset named by path, a DataLoader batch."""
    wheel = build_wheel(tmp_path / "build")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    python = venv / "bin" / "python"
    subprocess.run([python, "-m", "pip", "install", "-q", "--no-deps", str(wheel)], check=True)
    empty = tmp_path / "empty"
    empty.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": ""}
    u4d = [str(python), "-m", "u4d_aug.cli"]

    def run(*argv: str) -> str:
        result = subprocess.run(argv, cwd=empty, env=env, capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, result.stderr[-2000:]
        return result.stdout

    run(*u4d, "simulate", "--out", "world", "--sequences", "2", "--frames", "2", "--seed", "0", "--config",
        "sim/tiny")  # fmt: skip
    split = ['data.train_sequences=["00"]', 'data.val_sequences=["01"]']
    out = run(*u4d, "seg-train", "seg/tiny", "data.root=world", *split, "optim.steps=2", "eval_every=2",
              "--out", "seg", "--no-progress")  # fmt: skip
    assert "step 2: val mIoU" in out and (empty / "seg" / "model.pt").is_file()
    assert "batch (" in run(str(python), "-c", BANK_IN_A_LOADER)
