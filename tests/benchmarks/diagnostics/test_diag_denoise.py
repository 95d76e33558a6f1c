"""benchmarks/diagnostics/diag_denoise.py: one denoising call per log-SNR, checked with an oracle and a do-nothing
net."""

from __future__ import annotations

import json

import pytest
import torch

from tests.tiny_nets import load_script
from tests.tiny_worlds import write_tiny_world
from u4d_aug.diffusion import alpha_sigma
from u4d_aug.range_view import image_roughness

bench = load_script("diagnostics/diag_denoise")
LAMS = [0.0, 5.0, 11.0]


def target_images(generator: torch.Generator) -> torch.Tensor:
    """(2, 2, 8, 16) range images in [-0.9, 0.9] with a quarter of the pixels empty (-1)."""
    x0 = torch.rand((2, 2, 8, 16), generator=generator) * 1.8 - 0.9
    empty = torch.rand((2, 8, 16), generator=generator) < 0.25
    return torch.where(empty[:, None], -1.0, x0)


def test_an_oracle_net_removes_all_the_noise_and_a_silent_one_none(generator):
    target = target_images(generator)

    def oracle(x_t, lam, cond):  # the exact ε of x_t = α x0 + σ ε
        alpha, sigma = alpha_sigma(lam[0].double())
        return (x_t - float(alpha) * target) / float(sigma), None

    rows = bench.denoise_rows(oracle, target, None, LAMS, seed=0)
    assert [row["log_snr"] for row in rows] == LAMS
    assert all(row["error"] < 1e-5 for row in rows)
    assert all(row["roughness"] == pytest.approx(image_roughness(target)[0], abs=1e-5) for row in rows)
    noise = [row["noise"] for row in rows]
    assert noise == sorted(noise, reverse=True) and noise[0] > 0.5  # σ/α shrinks with log-SNR

    silent = bench.denoise_rows(lambda x_t, lam, cond: (torch.zeros_like(x_t), None), target, None, LAMS, seed=0)
    for row, same_noise in zip(silent, rows, strict=True):  # x̂0 = x_t/α: only the clamp to [-1, 1] can help
        assert row["noise"] == pytest.approx(same_noise["noise"]) and row["error"] <= row["noise"] + 1e-6
    assert silent[-1]["error"] == pytest.approx(silent[-1]["noise"], rel=0.05)  # σ/α ~ 0.004: nothing clamped


def test_run_on_tiny_nets_and_world(untrained_checkpoints, tmp_path):
    write_tiny_world(tmp_path / "world", tmp_path / "probs", num_scans=2)
    out = tmp_path / "denoise.json"
    nets = [f"{stage}={path}" for stage, path in untrained_checkpoints.items()]
    argv = ["--root", str(tmp_path / "world"), "--probs", str(tmp_path / "probs"), "--num", "2", "--out", str(out)]
    assert (
        bench.main([*argv, "--nets", *nets, "--log-snr", "0", "8", "--from-log-snr", "2", "--sampler", "ddim:4"]) == 0
    )
    result = json.loads(out.read_text())
    assert set(result["nets"]) == set(untrained_checkpoints) and result["log_snrs"] == [0.0, 8.0]
    assert result["last_call_log_snr"]["20"] == pytest.approx(5.07, abs=0.01)
    for name, net in result["nets"].items():
        assert net["stage"] == name and len(net["rows"]) == 2
        assert all(row["error"] <= row["noise"] + 1e-6 for row in net["rows"])  # untrained: ε̂ = 0
        assert [row["from_log_snr"] for row in net["trajectories"]] == [2.0] and net["real_bev_points_per_cell"] >= 0
    assert result["sampler"] == {
        "name": "ddim",
        "steps": 4,
        "grid": "time",
        "last_call_log_snr": pytest.approx(1.76, abs=0.01),
    }
    assert (
        "| 8 |" in out.with_suffix(".md").read_text()
        and "## Sampler trajectories" in out.with_suffix(".md").read_text()
    )
    assert bench.main([*argv, "--nets", *nets, "--sampler", "euler:4"]) == 2
    assert bench.main([*argv, "--nets", *nets, "--sampler", "ddim:4:logsnr"]) == 2  # ddim runs on the time grid only
    assert bench.main([*argv, "--nets", "no-equals-sign"]) == 2
    assert bench.main([*argv, "--nets", f"stage2={untrained_checkpoints['stage2']}", "--probs", str(tmp_path)]) == 2


def test_trajectories_follow_the_real_scan_up_to_the_start_and_the_net_after():
    from u4d_aug.data.sensors import get_sensor

    target = target_images(torch.Generator().manual_seed(1))
    sensor = get_sensor("hdl64")

    def oracle(x_t, lam, cond):
        alpha, sigma = alpha_sigma(lam[0].double())
        return (x_t - float(alpha) * target) / float(sigma), None

    def silent(x_t, lam, cond):
        return torch.zeros_like(x_t), None

    starts = [-100.0, 3.0, 100.0]  # the net from the first step, from the middle, never
    exact = bench.trajectory_rows(oracle, target, None, starts, "dpmpp2m-sde", 8, sensor, "linear", seed=0)
    assert [row["from_log_snr"] for row in exact] == starts
    assert all(row["error"] < 1e-4 for row in exact)  # an oracle net is the real scan whenever it takes over
    rows = bench.trajectory_rows(silent, target, None, starts, "dpmpp2m-sde", 8, sensor, "linear", seed=0)
    assert rows[2]["error"] < 1e-5  # handed the real x̂0 at every step: the real scan
    assert rows[0]["error"] > rows[1]["error"] > rows[2]["error"]  # the earlier a silent net takes over, the worse
