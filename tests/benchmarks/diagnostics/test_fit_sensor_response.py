"""benchmarks/diagnostics/fit_sensor_response.py: one rendered place against the real nuScenes keyframe(s)."""

from __future__ import annotations

import json
import math

import pytest

from tests.tiny_nets import load_script

bench = load_script("diagnostics/fit_sensor_response")


def test_fits_the_response_on_one_place(real_root, tmp_path, monkeypatch):
    nuscenes = real_root / "nuscenes_mmdet3d_demo"
    if not sorted(nuscenes.glob("**/LIDAR_TOP/*.pcd.bin")):
        pytest.skip(f"no nuScenes LIDAR_TOP scans under {nuscenes}")
    monkeypatch.setattr(bench, "REAL", nuscenes)
    monkeypatch.setattr(bench, "RESULTS", tmp_path / "world")
    assert bench.main(["--seeds", "7", "--places", "1", "--frames", "1", "--name", "fit"]) == 0
    result = json.loads((tmp_path / "world" / "fit.json").read_text())
    assert {"js_identity", "js_fitted", "quantiles", "quantile_levels", "seconds"} <= set(result)
    assert set(result["quantiles"]) == {"real", "sim_identity", "sim_fitted"}
    for values in result["quantiles"].values():
        assert len(values) == 4 and all(math.isfinite(v) for v in values) and values == sorted(values)
    assert 0.0 <= result["js_fitted"] < result["js_identity"] <= 1.0  # the fit brings sim closer to real


def test_no_real_scans_is_an_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench, "REAL", tmp_path / "empty")
    monkeypatch.setattr(bench, "RESULTS", tmp_path / "world")
    assert bench.main(["--places", "1", "--frames", "1"]) == 1
    assert "no nuScenes LIDAR_TOP scans" in capsys.readouterr().err and not (tmp_path / "world").exists()
