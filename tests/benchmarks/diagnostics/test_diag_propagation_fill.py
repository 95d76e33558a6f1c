"""benchmarks/diagnostics/diag_propagation_fill.py: the fill scores checked on hand-made frames, then a run on
tiny nets."""

from __future__ import annotations

import json
import math

import pytest
import torch

from tests.tiny_nets import TINY, load_script, save_checkpoint
from tests.tiny_worlds import write_posed_world
from u4d_aug.range_view import decode_depth, encode_depth

bench = load_script("diagnostics/diag_propagation_fill")
MAX_RANGE = 80.0


def frames_of(depth_m: list[float]) -> torch.Tensor:
    """(1, 2, 1, W) encoded frame of one ring of depths in metres (0 = no return), reflectance 0."""
    depth = torch.tensor(depth_m, dtype=torch.float32)
    encoded = torch.where(depth > 0, encode_depth(depth, MAX_RANGE), torch.tensor(-1.0))
    return torch.stack([encoded, torch.zeros_like(encoded)])[None, :, None, :]


def test_scores_count_only_the_unknown_pixels_and_the_seams():
    real = frames_of([10.0, 10.0, 20.0, 0.0, 30.0, 10.0])
    generated = frames_of([10.0, 12.0, 20.0, 5.0, 0.0, 10.0])
    m_u = torch.tensor([1.0, 0.0, 1.0, 0.0, 0.0, 1.0])[None, None, None, :]  # known: pixels 0, 2, 5
    s = bench.fill_scores(generated, real, m_u, MAX_RANGE)
    assert s["known"] == pytest.approx(0.5)
    assert s["returns"] == pytest.approx(1 / 3)  # unknown 1 agrees, 3 (gen return, real none) and 4 do not
    d = [float(decode_depth(encode_depth(torch.tensor(v), MAX_RANGE), MAX_RANGE)) for v in (10.0, 12.0, 20.0)]
    assert s["mae_m"] == pytest.approx(abs(d[1] - d[0]), rel=1e-4)  # only pixel 1 returns in both
    # seams with returns in both images at both ends: (0, 1) and (1, 2); pixel 4 does not return generated
    assert s["seam_m"] == pytest.approx((abs(d[1] - d[0]) + abs(d[2] - d[1])) / 2, rel=1e-4)
    assert s["seam_real_m"] == pytest.approx((0.0 + abs(d[2] - d[0])) / 2, rel=1e-4)

    everything_known = bench.fill_scores(generated, real, torch.ones_like(m_u), MAX_RANGE)
    assert everything_known["known"] == 1.0 and all(
        math.isnan(everything_known[k]) for k in ("returns", "mae_m", "seam_m")
    )


def test_the_summary_skips_windows_without_a_score():
    rows = [
        dict.fromkeys(bench.METRICS, 1.0),
        dict.fromkeys(bench.METRICS, 3.0),
        dict.fromkeys(bench.METRICS, math.nan),
    ]
    s = bench.summary(rows)
    assert s["mae_m"] == {"mean": 2.0, "std": pytest.approx(math.sqrt(2.0)), "n": 2}


def test_run_on_tiny_nets_and_a_posed_world(untrained_checkpoints, untrained_sequence_checkpoints, tmp_path):
    world, probs = tmp_path / "world", tmp_path / "probs"
    write_posed_world(world, probs, num_scans=3)
    one_net = save_checkpoint(tmp_path / "u4d.pt", TINY, ("diffusion.stage=u4d",))
    nets = [
        f"stage2={untrained_checkpoints['stage2']}",
        f"u4d={one_net}@stage2",  # a one-net u4d fills with its stage-2 task
        f"baseline={untrained_checkpoints['baseline']}",
        f"baseline_most={untrained_sequence_checkpoints['baseline']}",
    ]
    out = tmp_path / "fill"
    argv = ["--root", str(world), "--probs", str(probs), "--sequences", "00", "--frames", "3", "--steps", "2"]
    argv += ["--mean-data-root", str(world), "--out", str(out)]
    assert bench.main([*argv, "--nets", *nets]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert result["windows"] == 1 and set(result["nets"]) == {"stage2", "u4d", "baseline", "baseline_most"}
    assert result["nets"]["u4d"]["weights"] == f"{one_net}@stage2"
    for net in result["nets"].values():
        propagated, uncertain = net["propagated"], net["uncertain"]
        # the frames drive 2 m apart: most of frame 0 lands in frames 1-2, far more than the top 10 % of P_u
        assert propagated["known"]["mean"] > 2 * uncertain["known"]["mean"] > 0
        assert 0.0 <= propagated["returns"]["mean"] <= 1.0 and propagated["mae_m"]["mean"] >= 0.0
    same = result["per_window"]["stage2"]["propagated"][0]["known"]
    assert all(result["per_window"][n]["propagated"][0]["known"] == same for n in result["nets"])  # one condition
    assert "| propagated | baseline_most |" in out.with_suffix(".md").read_text()
    assert bench.main([*argv, "--nets", "no-equals-sign"]) == 2
    assert bench.main([*argv, "--nets", *nets, "--frames", "1"]) == 2
    stage1 = f"stage1={untrained_checkpoints['stage1']}"
    assert bench.main([*argv, "--nets", stage1]) == 2
    assert bench.main([*argv, "--nets", f"u4d={one_net}"]) == 2  # which task of the one net: @stage2
    assert bench.main([*argv, "--nets", f"stage2={untrained_checkpoints['stage2']}@stage2"]) == 2
