"""benchmarks/bench_generation_speed.py: --quick json (headline keys, paired ratio from its reps), shipped nets."""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

import pytest
import torch

from tests.tiny_nets import REPO, TINY, load_script, save_checkpoint

HEADLINE = ("u4d_s_per_scan", "baseline_s_per_scan", "paired_ratio", "anchor_s_per_scan")


bench = load_script("bench_generation_speed")


def save_tiny_baseline(path: Path) -> Path:
    """An untrained tiny-preset baseline checkpoint, as `u4d train-diffusion` writes it."""
    return save_checkpoint(path, TINY, ("diffusion.stage=baseline",))


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> tuple[dict, Path]:
    """main --quick to a tmp path, with a shipped baseline in a weights folder and a tiny anchor (1 forward)."""
    root = tmp_path_factory.mktemp("speed")
    weights = root / "weights"
    weights.mkdir()
    save_tiny_baseline(weights / "baseline.pt")
    out = root / "speed.json"
    argv = ["--quick", "--threads", "1", "--weights", str(weights), "--out", str(out)]
    argv += ["--anchor-preset", str(TINY), "--anchor-reps", "2", "--batches", "1", "2"]
    threads = torch.get_num_threads()
    try:
        assert bench.main(argv) == 0
    finally:
        torch.set_num_threads(threads)
    return json.loads(out.read_text()), out


def test_quick_json_has_the_headline_figures(quick_run):
    result, out = quick_run
    for key in HEADLINE:
        assert math.isfinite(result[key]) and result[key] > 0, key
    assert [run["sampler"] for run in result["samplers"]] == ["dpmpp2m", "ddpm"]
    assert result["headline_batch"] == 1 and result["machine"]["cores"] >= 1
    assert result["unet"][0]["fraction_of_matmul"] > 0 and result["nets"][0]["gflop_per_forward"] > 0
    assert "| U4D (stage 1 + stage 2) |" in out.with_suffix(".md").read_text()


def test_quick_headline_is_computed_from_the_repetitions(quick_run):
    result, _ = quick_run
    row = next(row for row in result["samplers"][0]["generation"] if row["batch"] == 1)
    ratios = [u / b for u, b in zip(row["u4d_s_per_scan_reps"], row["baseline_s_per_scan_reps"], strict=True)]
    assert len(ratios) == result["reps"] == 3
    assert result["paired_ratio"] == pytest.approx(statistics.median(ratios), rel=1e-12)
    assert result["u4d_s_per_scan"] == pytest.approx(statistics.median(row["u4d_s_per_scan_reps"]), rel=1e-12)
    assert result["baseline_s_per_scan"] == pytest.approx(statistics.median(row["baseline_s_per_scan_reps"]), rel=1e-12)
    anchor = result["anchor"]
    assert result["anchor_s_per_scan"] == pytest.approx(statistics.median(anchor["forward_s_reps"]) * 256, rel=1e-12)


def test_shipped_weights_are_used_and_named(quick_run):
    result, _ = quick_run
    sources = result["net_sources"]
    assert sources["baseline"].endswith("weights/baseline.pt")
    assert sources["stage1"] == sources["stage2"] == "configs/u4d/tiny.yaml (untrained)"


def test_paired_ratio_is_the_median_of_per_repetition_ratios():
    # ratios 2, 0.5, 3 -> 2; the ratio of the medians would be 3 / 3 = 1
    assert bench.paired_ratio([2.0, 3.0, 9.0], [1.0, 6.0, 3.0]) == 2.0


def test_checkpoint_sources_prefer_flags_then_weights_then_the_preset(tmp_path):
    for name in ("u4d.pt", "baseline.pt"):
        (tmp_path / name).touch()
    shipped = bench.checkpoint_sources(bench.parse_args(["--weights", str(tmp_path)]))
    one_net = {"stage1": tmp_path / "u4d.pt", "stage2": tmp_path / "u4d.pt"}  # the shipped U4D serves both stages
    assert shipped == {**one_net, "baseline": tmp_path / "baseline.pt"}
    args = bench.parse_args(["--weights", str(tmp_path), "--stage2", "runs/s2"])
    assert bench.checkpoint_sources(args) == {
        "stage1": tmp_path / "u4d.pt",  # the shipped one net's stage-1 task
        "stage2": Path("runs/s2"),
        "baseline": tmp_path / "baseline.pt",
    }
    overridden = bench.parse_args(["--weights", str(tmp_path), "--stage1-overrides", "net.base_channels=8"])
    assert bench.checkpoint_sources(overridden)["stage1"] is None
    for argv in (["--no-weights"], ["--quick"]):
        assert set(bench.checkpoint_sources(bench.parse_args(argv)).values()) == {None}
    assert bench.parse_args([]).weights == REPO / "weights"


def test_default_samplers_are_dpmpp2m_then_ddpm_32():
    args = bench.parse_args([])
    assert args.config == REPO / "configs" / "u4d" / "cpu_hdl64.yaml"
    assert bench.sampler_runs(args) == [
        {"sampler": "dpmpp2m", "steps": 20, "stage1_steps": 10},
        {"sampler": "ddpm", "steps": 32, "stage1_steps": 16},
    ]
    assert bench.sampler_runs(bench.parse_args(["--sampler", "ddpm"])) == [
        {"sampler": "ddpm", "steps": 32, "stage1_steps": 16}
    ]
    assert len(bench.sampler_runs(bench.parse_args(["--compare-ddpm-steps", "0"]))) == 1


def test_a_one_net_u4d_serves_both_stages_and_is_timed_and_sized_once(tmp_path):
    net = save_checkpoint(tmp_path / "u4d.pt", TINY, ("diffusion.stage=u4d",))
    baseline = save_tiny_baseline(tmp_path / "baseline.pt")
    out = tmp_path / "speed.json"
    argv = ["--quick", "--threads", "1", "--net", str(net), "--baseline", str(baseline), "--out", str(out)]
    argv += ["--anchor-reps", "0", "--batches", "1", "--compare-ddpm-steps", "0"]
    threads = torch.get_num_threads()
    try:
        assert bench.main(argv) == 0
    finally:
        torch.set_num_threads(threads)
    result = json.loads(out.read_text())
    assert result["net_sources"]["stage1"] == result["net_sources"]["stage2"] == str(net)
    assert [row["stage"] for row in result["training"]] == ["u4d", "baseline"]
    assert {row["stage"] for row in result["nets"] if "source" in row and row["source"] == str(net)} == {"u4d"}
    assert result["u4d_s_per_scan"] > 0 and result["baseline_s_per_scan"] > 0
    with pytest.raises(SystemExit):
        bench.parse_args(["--net", str(net), "--stage1", str(net)])
    two = bench.parse_args(["--stage1", str(net), "--stage2", str(baseline), "--baseline", str(baseline)])
    with pytest.raises(bench.InputError, match="is a baseline checkpoint, expected stage2"):
        bench.load_nets(two, bench.checkpoint_sources(two))
