"""benchmarks/reports/temporal_paired.py: per-sequence TTCE/CTC of banks drawn along the same trajectories, paired
differences with a bootstrap interval over sequences; banks whose poses differ are refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.tiny_nets import load_script
from u4d_aug.data.formats import write_calib, write_kitti_scan, write_poses
from u4d_aug.errors import InputError
from u4d_aug.metrics import temporal

paired = load_script("reports/temporal_paired")
FRAMES = 5


def room(rng: np.random.Generator) -> np.ndarray:
    """(3000, 3) world points on two walls and a floor: enough structure for ICP to lock on."""
    points = rng.uniform(-12, 12, (3000, 3))
    points[:1000, 0] = 12.0
    points[1000:2000, 1] = -9.0
    points[2000:, 2] = -1.5
    return points


def trajectory(step: float, yaw: float) -> np.ndarray:
    """(FRAMES, 4, 4) LiDAR poses driving `step` m per frame while turning `yaw` rad per frame."""
    poses = np.tile(np.eye(4), (FRAMES, 1, 1))
    for i in range(FRAMES):
        angle = yaw * i
        poses[i, :2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        poses[i, 0, 3] = step * i
    return poses


def write_bank(
    root: Path, rng: np.random.Generator, trajectories: list[np.ndarray], drift: float, moving: bool = True
) -> Path:
    """A bank whose frame i sees the room from pose i (from pose 0 unless `moving`), moved by a random `drift` m the
    poses do not know of; poses.txt always holds the trajectory."""
    calib = {key: np.eye(4)[:3] for key in ("P0", "P1", "P2", "P3", "Tr")}
    for s, poses in enumerate(trajectories):
        folder = root / "sequences" / f"{s:02d}"
        (folder / "velodyne").mkdir(parents=True)
        world = room(np.random.default_rng(s))
        for i, pose in enumerate(poses):
            seen_from = pose if moving else poses[0]
            local = (world - seen_from[:3, 3]) @ seen_from[:3, :3]  # (N, 3) sensor frame
            local = local + rng.normal(0.0, drift, 3) * (i > 0)  # frame 0 fixed, later frames drift
            scan = np.concatenate([local, np.full((len(local), 1), 0.5)], axis=1).astype(np.float32)
            write_kitti_scan(folder / "velodyne" / f"{i:06d}.bin", scan)
        write_calib(folder / "calib.txt", calib)
        write_poses(folder / "poses.txt", poses, calib)
    return root


@pytest.fixture(scope="module")
def banks(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("banks")
    trajectories = [trajectory(1.0, 0.0), trajectory(0.8, 0.02), trajectory(1.2, -0.03)]
    return {
        "exact": write_bank(root / "exact", np.random.default_rng(1), trajectories, drift=0.0),
        "drifting": write_bank(root / "drifting", np.random.default_rng(2), trajectories, drift=0.6),
    }


def test_paired_difference_on_known_values() -> None:
    reference = np.array([1.0, 2.0, 3.0, 4.0])
    other = reference + np.array([0.5, 0.5, -0.1, 0.5])
    entry = paired.paired_difference(reference, other, 2000, np.random.default_rng(0))
    assert entry["mean_diff"] == pytest.approx(0.35)
    assert entry["ci_low"] <= 0.35 <= entry["ci_high"]
    assert entry["ci_low"] >= -0.1 and entry["ci_high"] <= 0.5  # a mean of draws stays within the values
    assert entry["reference_lower_share"] == pytest.approx(0.75) and entry["n"] == 4
    with_nan = paired.paired_difference(np.array([1.0, np.nan]), np.array([2.0, 5.0]), 200, np.random.default_rng(0))
    assert with_nan["n"] == 1 and with_nan["mean_diff"] == pytest.approx(1.0)


def test_report_pairs_sequences_and_matches_the_pooled_scores(banks: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "paired"
    args = ["--bank", f"exact={banks['exact']}", "--bank", f"drifting={banks['drifting']}"]
    assert paired.main([*args, "--boot", "500", "--out", str(out), "--no-progress"]) == 0
    result = json.loads((tmp_path / "paired.json").read_text())
    assert result["reference"] == "exact" and result["sequences"] == ["00", "01", "02"]
    # The means are the pooled scores of u4d_aug.metrics.temporal over the bank's sequences.
    for name, root in banks.items():
        pooled = temporal.merge_interval_scores(
            temporal.ttce(*temporal.load_kitti_sequence(root / "sequences" / s)) for s in result["sequences"]
        )
        for k in ("3", "4"):
            assert result["means"][name]["ttce"][k] == pytest.approx(pooled.mean[int(k)])
    assert result["means"]["exact"]["ttce"]["3"] < 0.02  # frames moved exactly along their poses
    assert result["means"]["exact"]["ctc"]["1"] < 1e-6
    drift = result["paired"]["drifting"]
    for metric, k in (("ttce", "3"), ("ttce", "4"), ("ctc", "1"), ("ctc", "4")):
        entry = drift[metric][k]
        assert entry["n"] == 3 and entry["ci_low"] > 0  # the drifting bank is worse on every sequence
        assert entry["reference_lower_share"] == 1.0
    assert "exact" not in result["paired"]
    text = (tmp_path / "paired.md").read_text()
    assert "## Bank minus exact" in text and "| drifting |" in text and "(100 %)" in text


def test_banks_with_other_poses_or_sequences_are_refused(
    banks: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    other = write_bank(tmp_path / "other", np.random.default_rng(3), [trajectory(1.0, 0.0), trajectory(0.5, 0.0)], 0)
    other_poses = write_bank(
        tmp_path / "turned",
        np.random.default_rng(3),
        [trajectory(1.0, 0.0), trajectory(0.8, 0.02), trajectory(1.0, 0.0)],
        0,
    )
    with pytest.raises(InputError, match="sequences"):
        paired.score_banks({"exact": banks["exact"], "other": other}, progress=False)
    with pytest.raises(InputError, match=r"02/poses.txt: poses differ"):
        paired.score_banks({"exact": banks["exact"], "turned": other_poses}, progress=False)
    assert paired.main(["--bank", f"exact={banks['exact']}", "--out", str(tmp_path / "x")]) == 2
    assert "at least two banks" in capsys.readouterr().err
    assert paired.main(["--bank", "nobank", "--bank", "b=c", "--out", str(tmp_path / "x")]) == 2
    assert "expected NAME=DIR" in capsys.readouterr().err
    assert paired.main(["--bank", f"a={tmp_path}", "--bank", "b=c", "--out", str(tmp_path / "x")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_global_registration_metric_is_paired_like_the_others(banks: dict[str, Path], tmp_path: Path) -> None:
    """--metrics ttce_global: the same pairing with ICP from a global registration (u4d evaluate's TTCE-global)."""
    out = tmp_path / "global"
    args = ["--bank", f"exact={banks['exact']}", "--bank", f"drifting={banks['drifting']}", "--boot", "200"]
    assert paired.main([*args, "--metrics", "ttce_global", "--out", str(out), "--no-progress"]) == 0
    result = json.loads((tmp_path / "global.json").read_text())
    assert result["metrics"] == ["ttce_global"] and set(result["means"]["exact"]) == {"ttce_global"}
    for k in ("3", "4"):
        pooled = temporal.merge_interval_scores(
            temporal.ttce(*temporal.load_kitti_sequence(banks["exact"] / "sequences" / s), registration="global")
            for s in result["sequences"]
        )
        # RANSAC on open3d's threads is not bit-repeatable: the same score to well under a centimetre
        assert result["means"]["exact"]["ttce_global"][k] == pytest.approx(pooled.mean[int(k)], abs=2e-3)
        assert result["means"]["exact"]["ttce_global"][k] < 0.05  # exact frames: the registration finds the poses
        assert result["paired"]["drifting"]["ttce_global"][k]["mean_diff"] > 0.1  # 0.6 m of drift per axis
    assert "TTCE-global k=3 (m)" in (tmp_path / "global.md").read_text()
    assert paired.main([*args, "--metrics", "ttce,chamfer", "--out", str(out)]) == 2
