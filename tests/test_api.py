"""The public API: `import u4d_aug` stays cheap, every exported name resolves, the README's API section runs."""

from __future__ import annotations

import pkgutil
import re
import subprocess
import sys

import pytest

import segmentation
import u4d_aug
from tests.tiny_nets import REPO, save_random_checkpoint
from tests.tiny_worlds import write_toy_bank, write_toy_root


def test_import_is_cheap():
    code = "import sys, u4d_aug, segmentation; print(sorted({'torch', 'numpy'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("package", [u4d_aug, segmentation], ids=lambda p: p.__name__)
def test_every_exported_name_resolves(package):
    for name in package.__all__:
        assert getattr(package, name) is not None, name
    assert set(package.__all__) <= set(dir(package))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        package.nope  # noqa: B018


def test_exports_are_the_objects_of_their_modules():
    from segmentation.metrics import scan_ece
    from u4d_aug.data.collate import collate_scans
    from u4d_aug.pipeline import generate_u4d

    assert u4d_aug.collate_scans is collate_scans and u4d_aug.generate_u4d is generate_u4d
    assert segmentation.scan_ece is scan_ece


@pytest.mark.parametrize("package", [u4d_aug, segmentation], ids=lambda p: p.__name__)
def test_no_export_is_named_like_a_submodule(package):
    """Importing submodule X sets the package's attribute X to the module, which would hide an export named X."""
    submodules = {info.name for info in pkgutil.iter_modules(package.__path__)}
    assert not submodules & set(package.__all__)


def readme_api_code() -> str:
    """The first python block of the README's "## API" section."""
    text = (REPO / "README.md").read_text()
    section = text.split("\n## API\n", 1)[1].split("\n## ", 1)[0]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_api_section_runs(tmp_path, monkeypatch):
    """Files at the paths the README names: a labelled scan, a U4D run folder (one net for both stages), a bank."""
    write_toy_root(tmp_path / "data", sequences=("00",), frames=1)
    save_random_checkpoint(tmp_path / "runs" / "u4d" / "checkpoints" / "step_0000004.pt", "u4d")
    write_toy_bank(tmp_path / "banks" / "u4d")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(readme_api_code(), "README.md#API", "exec"), namespace)
    assert namespace["x0"].shape == (2, 64, 1024) and namespace["x0_u"].shape == (2, 64, 1024)
    assert namespace["h"].shape == (3000,) and len(namespace["uncertain"]) == 300
    assert 0.0 <= namespace["ece"] <= 1.0 and 0.0 <= namespace["miou"] <= 1.0
    assert len(namespace["clouds"]) == 2 and namespace["out"]["x0"].shape == (2, 2, 16, 64)
    assert namespace["batch"]["offsets"].shape == (3,) and namespace["batch"]["labels"] is None


def test_the_library_api_raises_one_line_input_errors_naming_the_argument(untrained_checkpoints):
    import numpy as np
    import torch

    from u4d_aug import GeneratedScans, InputError, SamplingSettings, generate_baseline, load_generator, project

    points = np.random.default_rng(0).uniform(-20, 20, (200, 4)).astype(np.float32)
    assert project(points, "hdl64").depth.shape == project(points, u4d_aug.get_sensor("hdl64")).depth.shape
    net = load_generator(untrained_checkpoints["baseline"])
    plain = SamplingSettings(steps=1, mean_start_below=None)  # a training checkpoint stores no training mean
    cases = [
        (lambda: project(points[:, :3], "hdl64"), r"points: expected shape \(N, 4\)"),
        (lambda: project(points, 64), "sensor: expected a Sensor or a sensor name"),
        (
            lambda: generate_baseline(net, 0, torch.Generator(), plain),
            "n: the number of samples must be an integer >= 1",
        ),
        (lambda: SamplingSettings(steps=0), "steps: expected an integer >= 1"),
        (lambda: generate_baseline(net, 1, torch.Generator(), 8), "settings: expected a SamplingSettings"),  # type: ignore[arg-type]
        (lambda: generate_baseline(net, 1, torch.Generator()), "export-weights --data-root.* mean_start_below=None"),
        (lambda: generate_baseline(net, 2, [torch.Generator()], plain), "generator: got 1 generators for a batch of 2"),
        (lambda: generate_baseline(net, 1, "seed", plain), "generator: expected a torch.Generator"),
        (lambda: GeneratedScans("baseline", [3], num=1), r"nets\[0\] is a int; expected load_generator"),
        (lambda: GeneratedScans("baseline", [str(untrained_checkpoints["baseline"]) + "x"], num=1), "not found"),
    ]
    for call, message in cases:
        with pytest.raises(InputError, match=message) as caught:
            call()
        assert "\n" not in str(caught.value)
    scans = GeneratedScans("baseline", [str(untrained_checkpoints["baseline"])], num=1, settings=plain)  # path: loaded
    assert next(iter(scans))["points"].shape[1] == 4
