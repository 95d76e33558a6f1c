"""`u4d weights [install PATH]`: the sha256-checked copy of the shipped nets (u4d_aug/weights_install.py), and a
wheel in a fresh venv that installs them and generates as the API does."""

from __future__ import annotations

import json

import pytest

from u4d_aug import weights_store
from u4d_aug.cli import main
from u4d_aug.errors import InputError
from u4d_aug.io import file_sha256
from u4d_aug.weights_install import install_weights
from u4d_aug.weights_store import TABLE_FORMAT, WEIGHTS_ENV


@pytest.fixture
def small_table(tmp_path, monkeypatch):
    """A shipped table of two small files (a.pt, b.pt) in tmp_path/src, so installs copy bytes, not 65 MB."""
    src = tmp_path / "src" / "weights"
    src.mkdir(parents=True)
    files = {}
    for name, data in (("a.pt", b"alpha" * 100), ("b.pt", b"beta" * 100)):
        (src / name).write_bytes(data)
        files[name] = {"sha256": file_sha256(src / name, 64), "bytes": len(data), "hash": name[0] * 16}
    table = tmp_path / "table.json"
    table.write_text(json.dumps({"format": TABLE_FORMAT, "files": files}))
    monkeypatch.setattr(weights_store, "TABLE_PATH", table)
    return src


def test_install_copies_checked_files_and_keeps_good_ones(small_table, tmp_path):
    target = tmp_path / "cache"
    done = install_weights(small_table.parent, target)  # a checkout: SOURCE/weights
    assert done == [("a.pt", "installed"), ("b.pt", "installed")]
    assert (target / "a.pt").read_bytes() == (small_table / "a.pt").read_bytes()
    assert sorted(path.name for path in target.iterdir()) == ["a.pt", "b.pt"]  # no temp file, no lock left
    assert install_weights(small_table, target)[0] == ("a.pt", "already installed")  # a folder of .pt files too


def test_install_refuses_bytes_that_are_not_the_shipped_ones_and_writes_nothing(small_table, tmp_path):
    (small_table / "b.pt").write_bytes(b"tampered")
    with pytest.raises(InputError, match=r"b\.pt: sha256 .* is not the shipped b\.pt .*nothing was installed"):
        install_weights(small_table, tmp_path / "cache")
    assert not (tmp_path / "cache").exists()


def test_install_names_what_the_source_lacks(small_table, tmp_path):
    (small_table / "b.pt").unlink()
    assert install_weights(small_table, tmp_path / "cache")[-1] == ("b.pt", f"not in {small_table}")
    with pytest.raises(InputError, match="no .pt files"):
        install_weights(tmp_path / "cache" / "..", tmp_path / "other")  # tmp_path: table.json and folders only


def test_the_weights_command_lists_installs_and_finds(small_table, no_installed, capsys):
    assert main(["weights"]) == 0
    out = capsys.readouterr().out
    assert "a.pt" in out and "not installed" in out and "u4d weights install PATH" in out
    target = no_installed / "elsewhere"
    assert main(["weights", "install", str(small_table.parent), "--weights-dir", str(target)]) == 0
    assert f"installed into {target}" in capsys.readouterr().out
    assert main(["--weights-dir", str(target), "weights"]) == 0
    out = capsys.readouterr().out
    assert f"{target / 'a.pt'}  ok" in out and "not installed" not in out
    assert main(["weights", "install"]) == 2
    assert "name the SOURCE" in capsys.readouterr().err


API_SCAN = """
import numpy as np, torch, u4d_aug
from u4d_aug import SamplingSettings, generate_u4d, load_generator, to_points
assert "site-packages" in u4d_aug.__file__, u4d_aug.__file__  # the installed copy, not the checkout
net = load_generator("weights/u4d.pt")  # the installed U4D: one net for both stages
x0 = generate_u4d(net, net, 1, [torch.Generator().manual_seed(0)], SamplingSettings())["x0"]  # seed 0 + sample 0
points = to_points(x0, net.config.sensor, net.config.row_mode)[0]
bank = np.fromfile("bank/sequences/00/velodyne/000000.bin", np.float32).reshape(-1, 4)
assert points.shape == bank.shape, (points.shape, bank.shape)
assert np.array_equal(points, bank), float(np.abs(points - bank).max())
print("same scan", points.shape)
"""


@pytest.mark.slow
def test_a_wheel_in_an_empty_folder_installs_the_nets_and_generates_as_the_api_does(tmp_path):
    """The issue's path for a new user: the wheel in a fresh venv, an empty folder, `u4d weights install CHECKOUT`,
    `u4d generate u4d/generate_hdl64 --num 1`; its scan equals `generate_u4d` with the default SamplingSettings."""
    import os
    import subprocess
    import sys

    from tests.tiny_nets import REPO
    from tests.u4d_aug.test_presets import build_wheel

    wheel = build_wheel(tmp_path / "build")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    python = str(venv / "bin" / "python")
    subprocess.run([python, "-m", "pip", "install", "-q", "--no-deps", str(wheel)], check=True)
    empty = tmp_path / "empty"
    empty.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": "", "XDG_CACHE_HOME": str(tmp_path / "cache")}
    env.pop(WEIGHTS_ENV, None)

    def run(*argv: str) -> str:
        result = subprocess.run(argv, cwd=empty, env=env, capture_output=True, text=True, timeout=900)
        assert result.returncode == 0, result.stderr[-2000:]
        return result.stdout

    u4d = [python, "-m", "u4d_aug.cli"]
    before = subprocess.run([*u4d, "generate", "u4d/generate_hdl64", "--out", "bank", "--num", "1"], cwd=empty,
                            env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert before.returncode == 2 and "u4d weights install PATH" in before.stderr and not (empty / "bank").exists()
    assert f"installed into {tmp_path / 'cache' / 'u4d' / 'weights'}" in run(*u4d, "weights", "install", str(REPO))
    assert "not installed" not in run(*u4d, "weights")
    run(*u4d, "generate", "u4d/generate_hdl64", "--out", "bank", "--num", "1", "--no-progress")
    assert "same scan" in run(python, "-c", API_SCAN)
