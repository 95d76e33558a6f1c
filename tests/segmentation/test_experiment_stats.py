"""The statistics of `u4d experiment`'s paired comparisons: 95 % confidence interval of the mean paired difference,
the seeds a difference of that size and spread needs for p < 0.05, and per-class paired differences."""

from __future__ import annotations

import math

import pytest
from scipy import stats

from segmentation.experiment import aggregate, paired_arms, paired_differences, results_markdown, seeds_needed


def test_confidence_interval_is_the_t_interval_and_matches_the_test():
    reference = {0: 0.40, 1: 0.50, 2: 0.45}
    other = {0: 0.41, 1: 0.52, 2: 0.48}  # differences 0.01, 0.02, 0.03: mean 0.02, std 0.01
    paired = paired_differences(reference, other)
    half = stats.t.ppf(0.975, 2) * 0.01 / math.sqrt(3)  # 4.303 * 0.00577 = 0.0248
    assert paired["ci95"] == pytest.approx([0.02 - half, 0.02 + half])
    assert paired["ci95"][0] < 0 < paired["ci95"][1] and paired["p"] > 0.05  # the interval and the test agree
    assert paired_differences({0: 0.4}, {0: 0.5})["ci95"] is None  # one seed: no interval


def test_seeds_needed():
    # mean 0.02, std 0.01: n = 3 gives t*s/sqrt(n) = 0.0248 > 0.02; n = 4: 3.182 * 0.005 = 0.0159 < 0.02
    assert seeds_needed(0.02, 0.01) == 4
    assert seeds_needed(-0.02, 0.01) == 4  # the sign does not matter
    assert seeds_needed(0.0, 0.01) is None
    assert seeds_needed(0.001, 0.05) is None  # more than 200 seeds
    assert seeds_needed(0.01, 0.0) == 2
    assert paired_differences({0: 0.4, 1: 0.5, 2: 0.45}, {0: 0.41, 1: 0.52, 2: 0.48})["seeds_needed"] == 4


def entry(arm: str, values: dict[int, tuple[float, float, float]]) -> dict:
    """An arm entry with runs of (mIoU, ECE, car IoU) per seed."""
    runs = [
        {"seed": s, "miou": m, "ece_per_scan": e, "iou": {"car": c, "road": 0.9}} for s, (m, e, c) in values.items()
    ]
    return {"arm": arm, "backbone": "minkunet", "runs": runs}


def test_per_class_paired_differences_and_report():
    ref = entry("mt", {0: (0.40, 0.05, 0.60), 1: (0.42, 0.05, 0.62), 2: (0.41, 0.05, 0.61)})
    new = entry("mt+u4d", {0: (0.41, 0.04, 0.70), 1: (0.43, 0.05, 0.71), 2: (0.42, 0.04, 0.72)})
    paired = paired_arms(ref, new)
    assert paired["iou"]["car"]["mean"] == pytest.approx(0.10) and paired["iou"]["car"]["ci95"][0] > 0
    assert paired["iou"]["road"]["mean"] == 0 and paired["iou"]["road"]["seeds_needed"] is None
    row = {**paired, "arm": "mt+u4d", "reference": "mt", "backbone": "minkunet"}
    results = {"config": {}, "arms": [], "contrasts": [row]}
    markdown = results_markdown(results)
    assert "| mt+u4d | mt | minkunet | +10.0* | +0.0 |" in markdown  # car gains, and its interval excludes 0
    assert "| 95 % CI |" in markdown and "seeds for p < 0.05" in markdown


def test_distance_bands_in_the_report():
    def with_bands(e: dict, near: list[float]) -> dict:
        for run, value in zip(e["runs"], near):
            run["bands"] = [{"range": [0.0, 10.0], "miou": value}, {"range": [50.0, None], "miou": 0.2}]
        return e

    ref = with_bands(entry("mt", {0: (0.40, 0.05, 0.6), 1: (0.42, 0.05, 0.6)}), [0.50, 0.52])
    new = with_bands(entry("mt+u4d", {0: (0.41, 0.04, 0.6), 1: (0.43, 0.05, 0.6)}), [0.55, 0.58])
    paired = paired_arms(ref, new)
    assert list(paired["bands"]) == ["0-10 m", ">= 50 m"]
    assert paired["bands"]["0-10 m"]["mean"] == pytest.approx(0.055) and paired["bands"][">= 50 m"]["mean"] == 0
    arms = [{**e, "status": "done", **aggregate(e["runs"])} for e in (ref, new)]
    row = {**paired, "arm": "mt+u4d", "reference": "mt", "backbone": "minkunet"}
    markdown = results_markdown({"config": {}, "arms": arms, "contrasts": [row]})
    assert "| mt | minkunet | 51.00 ± 1.41 | 20.00 ± 0.00 |" in markdown  # mean ± std over seeds per band
    assert "| mt+u4d | mt | minkunet | +5.5 | +0.0 |" in markdown  # +5, +6 points: 2 seeds, the CI holds 0


def test_learning_curves_from_the_run_logs(tmp_path):
    from segmentation.experiment import run_curves
    from segmentation.plots import plot_arm_curves
    from segmentation.records import log_curves
    from u4d_aug.io import append_jsonl

    runs = []
    for seed in (0, 1):
        out = tmp_path / f"seed{seed}"
        for step in (10, 20, 30):
            append_jsonl(out / "log.jsonl", {"step": step, "loss": 3.0 - step / 10 + seed, "lr": 0.01})
        append_jsonl(out / "log.jsonl", {"step": 30, "val_miou": 0.4 + seed / 10})
        runs.append({"seed": seed, "out_dir": str(out), "curves": log_curves(out / "log.jsonl")})
    curves = run_curves(runs)
    assert curves["loss"][1] == [(10.0, 3.0), (20.0, 2.0), (30.0, 1.0)]
    assert curves["val_miou"] == [[(30.0, 0.4)], [(30.0, 0.5)]]
    png = tmp_path / "curves.png"
    plot_arm_curves({"mt": curves, "empty": {"loss": [[]], "val_miou": []}}, png)
    assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
