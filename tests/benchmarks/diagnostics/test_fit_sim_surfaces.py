"""benchmarks/diagnostics/fit_sim_surfaces.py: the surface fit on one rendered frame against the real frames."""

from __future__ import annotations

import json
import math
import sys

from tests.tiny_nets import load_script

bench = load_script("diagnostics/fit_sim_surfaces")
GRID = {name: (float(grid.min()), float(grid.max())) for name, grid in bench.GRIDS.items()}


def test_fits_the_materials_of_one_frame(kitti_root, tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "RESULTS", tmp_path / "world")
    argv = ["fit_sim_surfaces.py", "--places", "1", "--frames", "1", "--real", str(kitti_root)]
    monkeypatch.setattr(sys, "argv", argv)
    assert bench.main() == 0
    result = json.loads((tmp_path / "world" / "sim_surface_fit.json").read_text())
    assert result["places"] == 1 and result["frames"] == 1 and result["set"] == bench.FIT_SET
    assert 0.0 <= result["intensity_noise"] <= 0.08
    for key in ("mean", "weighted"):
        assert math.isfinite(result[key]) and 0.0 <= result[key] <= 1.0
    assert result["materials"], "no material had enough returns to fit"
    start = {material.name: material.zero_prob for material in bench.MATERIALS}
    for name, fit in result["materials"].items():
        assert name in start and set(fit) == set(GRID)
        assert GRID["gain"][0] <= fit["gain"] <= GRID["gain"][1]
        assert GRID["speckle"][0] <= fit["speckle"] <= GRID["speckle"][1]
        if name in bench.ZERO_FIT:
            assert 0.0 <= fit["zero"] <= GRID["zero"][1]
        else:  # not fitted: the material's own zero probability
            assert fit["zero"] == start[name]
