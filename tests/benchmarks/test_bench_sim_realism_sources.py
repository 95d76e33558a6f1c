"""benchmarks/bench_sim_realism_sources.py: the real sources of ../shared/data/real, one tiny world per preset."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from tests.tiny_nets import load_script

bench = load_script("bench_sim_realism_sources")
JS_KEYS = ("range_js", "elevation_js", "ring_js", "intensity_js")


@pytest.fixture(scope="module")
def out(real_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The benchmark on 1 place x 2 frames per preset and seed 0, written to a temp folder."""
    out = tmp_path_factory.mktemp("sources")
    argv = ["--seeds", "0", "--sequences", "1", "--frames", "2", "--out", str(out), "--real", str(real_root)]
    assert bench.main([*argv, "--name", "tiny"]) == 0
    return out


@pytest.fixture(scope="module")
def result(out: Path) -> dict:
    return json.loads((out / "tiny.json").read_text())


def test_sources_found_skipped_and_absent(real_root: Path) -> None:
    sources, skipped = bench.find_sources(real_root)
    assert {s.name: (s.sensor, len(s.scans), s.labelled) for s in sources} == {
        "nuscenes_mmdet3d_demo": ("hdl32", 1, False),
        "semantickitti_00_labelled": ("hdl64", 3, True),
        "semantickitti_00_unlabelled": ("hdl64", 3, False),
    }
    status = {entry["name"]: entry for entry in skipped}
    assert status["nuscenes_mmdet3d_tests"]["status"] == "skipped"
    assert "40, 400, 100 points" in status["nuscenes_mmdet3d_tests"]["reason"]
    assert status["semantickitti_mmdet3d_tests_00_labelled"]["status"] == "skipped"
    assert status["kitti_object"]["status"] == "absent" and "training/velodyne" in status["kitti_object"]["reason"]


def test_every_source_has_bounded_metrics(result: dict) -> None:
    assert set(result["real"]) == {"nuscenes_mmdet3d_demo", "semantickitti_00_labelled", "semantickitti_00_unlabelled"}
    for preset, world in result["worlds"].items():
        for source, row in world["summary"].items():
            assert row["same_sensor"] == (world["sensor"] == result["real"][source]["sensor"]), (preset, source)
            for key in JS_KEYS:
                assert 0.0 < row[key]["mean"] <= 1.0, (preset, source, key)
            labelled = result["real"][source]["labelled"]
            assert (row["class_intensity_js"] is not None) == labelled
            if labelled:
                assert 0.0 < row["class_intensity_js"]["mean"] <= 1.0
            assert row["points_per_scan"]["mean"] > 10_000 and 0.0 <= row["mixed_share"]["mean"] <= 1.0
            assert math.isfinite(row["roughness_mm"]["mean"]) and row["roughness_mm"]["mean"] > 0


def test_outputs_name_the_absent_and_skipped_sources(out: Path, result: dict) -> None:
    text = (out / "tiny.md").read_text()
    assert "absent: `kitti_object`" in text and "skipped: `nuscenes_mmdet3d_tests`" in text
    assert (out / "tiny_remission.png").stat().st_size > 0
    assert [entry["name"] for entry in result["skipped"]][-1] == "kitti_object"


def test_a_source_against_itself_is_at_distance_zero(result: dict) -> None:
    pairs = result["real_vs_real"]
    for name, row in pairs.items():
        assert all(row[name][key] == 0.0 for key in JS_KEYS), name
    assert set(
        pairs["semantickitti_00_labelled"]["semantickitti_00_labelled"]["class_intensity_js_per_class"].values()
    ) == {0.0}
    # seq 00 frames 0-2 against frames 3-5 (0.35 s and 2-3.5 m later): the floor of one place
    assert pairs["semantickitti_00_labelled"]["semantickitti_00_unlabelled"]["range_js"] == pytest.approx(
        0.081, abs=1e-3
    )


def test_nuscenes_scan_is_read_without_ego_returns_on_a_0_1_scale(result: dict) -> None:
    real = result["real"]["nuscenes_mmdet3d_demo"]
    assert real["points_per_scan"] == 34688 - 8029  # SOURCES.md: 8,029 returns within 1 m (the ego car)
    hist = real["intensity_hist"]
    # intensity / 255: unscaled 0-255 values would all pile up in the last bin (0.95-1)
    assert sum(hist) == real["points_per_scan"] and hist[-1] / sum(hist) < 0.01


def test_missing_real_folder_is_a_clear_error(tmp_path: Path, capsys) -> None:
    assert bench.main(["--real", str(tmp_path / "none"), "--out", str(tmp_path)]) == 1
    assert "no real scans at" in capsys.readouterr().err
