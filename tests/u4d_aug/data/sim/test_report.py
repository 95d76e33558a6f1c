"""`u4d sim-report` (u4d_aug/data/sim/report.py): ring recovery, histograms, JS distances, per-place spread, CLI."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.distance import jensenshannon

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.data.formats import load_kitti_frame, read_kitti_scan, write_kitti_scan
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.report import (
    LABEL_RANGE,
    RANGE_BINS,
    add_sim_report_arguments,
    compare,
    dataset_stats,
    frames_stats,
    place_spread,
    plot_report,
    rings_from_storage,
    run_sim_report,
)
from u4d_aug.data.sim.writer import simulate
from u4d_aug.errors import InputError

TINY = REPO / "configs" / "sim" / "tiny.yaml"


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("simreport") / "w"
    simulate(out, sequences=2, frames=3, seed=3, config=load_config(SimConfig, TINY, []), progress=False)
    return out


def _ring_major_scan(rings: int, per_ring: int) -> np.ndarray:
    """Synthetic KITTI-ordered scan: each ring sweeps the azimuth once, starting facing forward."""
    azimuth = np.tile(np.linspace(0.0, 2 * np.pi, per_ring, endpoint=False), rings)
    elevation = np.repeat(np.linspace(0.03, -0.4, rings), per_ring)
    r = 10.0
    xyz = np.column_stack(
        [r * np.cos(elevation) * np.cos(azimuth), r * np.cos(elevation) * np.sin(azimuth), r * np.sin(elevation)]
    )
    return np.column_stack([xyz, np.zeros(len(xyz))]).astype(np.float32)


def test_rings_recovered_from_storage_order() -> None:
    scan = _ring_major_scan(rings=5, per_ring=600)
    np.testing.assert_array_equal(rings_from_storage(scan), np.repeat(np.arange(5), 600))


def test_frames_stats_sums_scans_as_dataset_stats_does(tiny_world: Path) -> None:
    scans = sorted(tiny_world.rglob("velodyne/*.bin"))
    frames = [load_kitti_frame(s, s.parent.parent / "labels" / f"{s.stem}.label") for s in scans]
    from_root = dataset_stats(tiny_world)
    given_rings = frames_stats((f.points, f.semantic, rings_from_storage(f.points)) for f in frames)
    for key in ("range_hist", "elevation_hist", "intensity_all", "intensity_hist", "ring_counts", "roughness_hist"):
        np.testing.assert_array_equal(given_rings[key], from_root[key])
    assert given_rings["edges"] == from_root["edges"] and given_rings["points_per_scan"] == from_root["points_per_scan"]
    # every return's remission, near or far; the per-class histograms hold the labelled returns within LABEL_RANGE
    assert from_root["intensity_all"].sum() == sum(len(f.points) for f in frames)
    near = sum(int((np.linalg.norm(f.points[:, :3], axis=1) <= LABEL_RANGE).sum()) for f in frames)
    assert from_root["intensity_hist"].sum() == near
    wide = frames_stats(((f.points, None, None) for f in frames), elevation_bins=np.arange(-90.0, 90.01, 0.5))
    assert wide["elevation_hist"].sum() == sum(len(f.points) for f in frames) and "intensity_hist" not in wide
    with pytest.raises(InputError, match="no scans"):
        frames_stats([])


def test_identical_roots_have_zero_distance(tiny_world: Path) -> None:
    report, sim, _ = compare(tiny_world, tiny_world)
    assert report["range_js"] == pytest.approx(0.0, abs=1e-7)
    assert report["elevation_js"] == pytest.approx(0.0, abs=1e-7)
    assert report["frames"] == {"sim": 6, "real": 6}
    shares = [s["sim"] for s in report["class_share"].values()]
    assert sum(shares) == pytest.approx(1.0)
    assert sum(s["sim"] for s in report["range_share"].values()) == pytest.approx(1.0, abs=1e-6)
    ranges = [np.linalg.norm(read_kitti_scan(p)[:, :3], axis=1) for p in tiny_world.rglob("*.bin")]
    assert sim["range_hist"].sum() == sum(int((r < RANGE_BINS[-1]).sum()) for r in ranges)  # every point 0-80 m


def test_place_spread_is_the_js_of_each_sequence_start(tiny_world: Path) -> None:
    pooled = np.zeros(len(RANGE_BINS) - 1)
    for scan in sorted(tiny_world.rglob("*.bin")):
        pooled += np.histogram(np.linalg.norm(read_kitti_scan(scan)[:, :3], axis=1), RANGE_BINS)[0]
    spread = place_spread(tiny_world, 2, pooled)
    assert spread["places"] == 2 and set(spread["per_place"]) == {"00", "01"}
    for seq, value in spread["per_place"].items():
        scans = sorted((tiny_world / "sequences" / seq / "velodyne").glob("*.bin"))[:2]
        hist = sum(np.histogram(np.linalg.norm(read_kitti_scan(s)[:, :3], axis=1), RANGE_BINS)[0] for s in scans)
        assert value == pytest.approx(float(jensenshannon(hist, pooled, base=2)))
        assert 0.0 < value < 1.0  # one place of a 2-sequence world is not the pool
    assert spread["min"] <= spread["median"] <= spread["max"]
    assert place_spread(tiny_world, 4, pooled)["places"] == 0  # no sequence holds 4 scans


def test_shifted_ranges_raise_the_distance(tiny_world: Path, tmp_path: Path) -> None:
    far = tmp_path / "far"
    for scan in sorted(tiny_world.rglob("*.bin")):
        points = read_kitti_scan(scan)
        points[:, :3] *= 1.5  # every return 50 % farther
        write_kitti_scan(far / scan.relative_to(tiny_world), points)
    report, _, _ = compare(far, tiny_world)
    assert 0.2 < report["range_js"] <= 1.0


def test_cli_report_against_real_scans(tiny_world: Path, kitti_root: Path, tmp_path: Path, capsys) -> None:
    parser = argparse.ArgumentParser()
    add_sim_report_arguments(parser)
    png = tmp_path / "report.png"
    assert run_sim_report(parser.parse_args([str(tiny_world), "--real", str(kitti_root), "--png", str(png)])) == 0
    text = capsys.readouterr().out
    assert "range JS distance" in text and "one simulated place (6 consecutive scans)" not in text  # 3 < 6 frames
    assert png.is_file() and png.stat().st_size > 10_000
    assert run_sim_report(parser.parse_args([str(tiny_world), "--real", str(kitti_root), "--json"])) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == {"sim": 6, "real": 6}
    assert report["points_per_scan"]["real"] == pytest.approx(124301.8, abs=0.1)  # real seq 00, frames 0-5
    assert 0.0 < report["range_js"] < 1.0
    assert report["class_share"]["road"]["real"] > 0.2  # labelled real frames 0-2: ~27 % road
    assert report["range_js_place_spread"]["places"] == 0


def test_root_without_scans_is_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no sequences"):
        compare(tmp_path, tmp_path)


def test_per_class_remission_and_edges_against_real_scans(tiny_world: Path, kitti_root: Path, tmp_path: Path, capsys):
    parser = argparse.ArgumentParser()
    add_sim_report_arguments(parser)
    png = tmp_path / "remission.png"
    args = parser.parse_args([str(tiny_world), "--real", str(kitti_root), "--intensity-png", str(png), "--json"])
    assert run_sim_report(args) == 0
    report = json.loads(capsys.readouterr().out)
    js = report["intensity_js"]
    assert {"road", "sidewalk", "building", "vegetation"} <= set(js["per_class"])
    assert all(0.0 < v < 1.0 for v in js["per_class"].values())
    assert min(js["per_class"].values()) <= js["mean"] <= max(js["per_class"].values())
    assert js["zero_share"]["road"]["real"] == pytest.approx(0.125, abs=0.01)  # real seq 00, frames 0-2, <= 50 m
    real_edges = report["edges"]["real"]
    assert 10.0 < real_edges["roughness_median_mm"] < 25.0 and 0.0 < real_edges["mixed_share_of_edges"] < 0.3
    assert png.is_file() and png.stat().st_size > 10_000
    same, _, _ = compare(tiny_world, tiny_world)
    assert same["intensity_js"]["mean"] == 0.0


def test_report_figure_names_classes_and_units(tiny_world: Path, kitti_root: Path, tmp_path: Path, monkeypatch):
    import matplotlib.pyplot as plt

    figures = []
    monkeypatch.setattr("u4d_aug.viz.save_figure", lambda fig, path, dpi=110: figures.append(fig) or path)
    report, sim, real = compare(tiny_world, kitti_root, 2)
    plot_report(tmp_path / "r.png", report, sim, real)
    sim_bev, sim_range, real_bev, real_range = figures[0].axes[4:8]
    assert sim_bev.get_legend() is None  # one legend for both BEVs, right of the last
    names = [text.get_text() for text in real_bev.get_legend().get_texts()]
    assert {"road", "car", "building"} <= set(names) and names[-1] == "ignore"
    for ax in (sim_bev, real_bev):
        assert ax.get_xlabel() == "x [m] (forward)" and ax.get_ylabel() == "y [m] (left)" and ax.get_aspect() == 1.0
    assert [child.get_ylabel() for ax in (sim_range, real_range) for child in ax.child_axes] == ["range [m]"] * 2
    plt.close(figures[0])
