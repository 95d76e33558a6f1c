"""The scripts in examples/ run as a user runs them (a subprocess, outside the repository) on tiny inputs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.tiny_nets import REPO
from tests.tiny_worlds import write_toy_bank, write_toy_root
from u4d_aug.data.formats import read_kitti_label
from u4d_aug.data.labels import map_semantickitti
from u4d_aug.io import atomic_save_npy

EXAMPLES = REPO / "examples"


def run_example(name: str, *args: str, cwd: Path) -> str:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_plug_bank_into_training_loop(tmp_path):
    bank = write_toy_bank(tmp_path / "bank")
    labeled = write_toy_root(tmp_path / "toy", sequences=("00",), frames=2)
    out = run_example(
        "plug_bank_into_training_loop.py", str(bank), "--labeled", str(labeled), "--steps", "2", cwd=tmp_path
    )
    lines = out.splitlines()
    assert [line.split(":")[0] for line in lines] == ["step 1", "step 2"]
    assert all("2 bank scans" in line or "1 bank scans" in line for line in lines)
    assert all(np.isfinite(float(line.rsplit("loss ", 1)[1])) for line in lines)


def test_ece_of_saved_probabilities(tmp_path):
    """Probabilities 0.8 on the true class and 0.2 on car: correct everywhere, 0.2 over-cautious but on car points."""
    data = write_toy_root(tmp_path / "toy", sequences=("00",), frames=2)
    for frame in ("000000", "000001"):
        semantic, _ = read_kitti_label(data / "sequences" / "00" / "labels" / f"{frame}.label")
        labels = map_semantickitti(semantic)
        probs = np.zeros((len(labels), 19), np.float16)
        probs[:, 0] = 0.2
        probs[np.arange(len(labels)), np.where(labels == 19, 1, labels)] += np.float16(0.8)  # ignore: any row
        atomic_save_npy(tmp_path / "probs" / "sequences" / "00" / "probs" / f"{frame}.npy", probs)
    png = tmp_path / "reliability.png"
    summary = json.loads(
        run_example("ece_of_saved_probabilities.py", "probs", "toy", "--json", "--png", str(png), cwd=tmp_path)
    )
    assert summary["scans"] == 2
    # car points (train id 0) get 1.0, the others 0.8: ECE = 0.2 x the share of non-car points among the labelled,
    # 2100 of 2850 in each toy scan (1500 road + 600 building; 750 car; 150 unlabelled -> ignore)
    assert summary["ece_pooled"] == pytest.approx(0.2 * 2100 / 2850, abs=1e-3)
    assert summary["ece_per_scan"] == pytest.approx(summary["ece_pooled"]) and summary["accuracy"] == 1.0
    assert png.read_bytes()[:4] == b"\x89PNG"
    text = run_example("ece_of_saved_probabilities.py", "probs", "toy", cwd=tmp_path)
    assert text.startswith("scans 2: ECE per scan")
