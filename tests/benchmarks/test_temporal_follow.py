"""benchmarks/temporal_follow.py: ICP translations against the conditioning poses tell a sequence that follows its
motion (gain ~1, TTCE ~0) from a static one (gain ~0, TTCE against standing still ~0); bad input in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.benchmarks.reports.test_temporal_paired import trajectory, write_bank
from tests.tiny_nets import load_script

follow = load_script("temporal_follow")


def test_follow_scores_on_known_translations() -> None:
    truths = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    exact = follow.follow_scores(truths, truths)
    assert exact["gain"] == pytest.approx(1.0) and exact["ttce_poses"] == 0.0 and exact["pairs"] == 2
    assert exact["ttce_still"] == pytest.approx(0.5) and exact["pose_m"] == pytest.approx(1.5)
    half = follow.follow_scores(truths / 2, truths)
    assert half["gain"] == pytest.approx(0.5) and half["icp_m"] == pytest.approx(0.75)
    still = follow.follow_scores(np.zeros((2, 3)), truths)
    assert still["gain"] == 0.0 and still["ttce_still"] == 0.0 and still["ttce_poses"] == pytest.approx(0.5)
    assert np.isnan(follow.follow_scores(np.zeros((0, 3)), np.zeros((0, 3)))["gain"])


def test_a_moving_bank_follows_and_a_static_one_does_not(tmp_path: Path) -> None:
    trajectories = [trajectory(1.0, 0.0), trajectory(0.8, 0.02)]
    moving = write_bank(tmp_path / "moving", np.random.default_rng(1), trajectories, drift=0.0)
    static = write_bank(tmp_path / "static", np.random.default_rng(1), trajectories, drift=0.0, moving=False)
    out = tmp_path / "res" / "follow"
    assert follow.main(["--bank", f"moving={moving}", "--bank", f"static={static}", "--out", str(out)]) == 0
    result = json.loads((tmp_path / "res" / "follow.json").read_text())
    for k in ("1", "3"):
        m, s = result["banks"]["moving"][k], result["banks"]["static"][k]
        assert m["pairs"] == s["pairs"] == 2 * (5 - int(k))
        assert m["gain"] == pytest.approx(1.0, abs=0.05) and m["ttce_poses"] < 0.02
        assert abs(s["gain"]) < 0.05 and s["ttce_still"] < 0.02
        assert s["ttce_poses"] == pytest.approx(s["pose_m"] / 3, rel=0.1)  # all motion is along x: |t| / 3
    assert result["figure"] == "follow.png" and (tmp_path / "res" / "follow.png").stat().st_size > 0
    assert "| static | 3 |" in (tmp_path / "res" / "follow.md").read_text() and result["registration"] == "icp"
    argv = ["--bank", f"moving={moving}", "--registration", "global", "--out", str(tmp_path / "res" / "global")]
    assert follow.main(argv) == 0
    result = json.loads((tmp_path / "res" / "global.json").read_text())
    assert result["registration"] == "global" and result["banks"]["moving"]["3"]["gain"] == pytest.approx(1, abs=0.05)
    assert "FPFH + RANSAC" in (tmp_path / "res" / "global.md").read_text()


def test_bad_banks_are_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert follow.main(["--out", str(tmp_path / "x")]) == 2
    assert "at least one" in capsys.readouterr().err
    assert follow.main(["--bank", "nobank", "--out", str(tmp_path / "x")]) == 2
    assert "expected NAME=DIR" in capsys.readouterr().err
    assert follow.main(["--bank", f"a={tmp_path}", "--out", str(tmp_path / "x")]) == 2
    assert "is not a folder" in capsys.readouterr().err
