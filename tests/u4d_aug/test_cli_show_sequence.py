"""`u4d show SEQUENCE_DIR` (u4d_aug/cli.py): every frame's depth image and a BEV of the frames moved by their poses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from u4d_aug.cli import main
from u4d_aug.data.formats import write_calib, write_kitti_scan, write_poses
from u4d_aug.trajectory import poses_from_motion, straight_motion

IDENTITY_CALIB = {"P0": np.eye(3, 4), "Tr": np.eye(3, 4)}


def write_sequence(folder, frames: int = 3, step: float = 1.5):
    """One static world seen from `frames` poses `step` m apart: frame i holds the world in sensor frame i."""
    rng = np.random.default_rng(0)
    world = np.concatenate([rng.uniform(-30, 30, (500, 2)), rng.uniform(-1.5, 1.5, (500, 1))], axis=1)
    poses = poses_from_motion(straight_motion(frames, step, yaw_rate=0.1))
    for i, pose in enumerate(poses):
        local = (world - pose[:3, 3]) @ pose[:3, :3]  # T_i^-1 applied to the world points
        write_kitti_scan(folder / "velodyne" / f"{i:06d}.bin", np.c_[local, np.full(len(local), 0.5)].astype("f4"))
    write_calib(folder / "calib.txt", IDENTITY_CALIB)
    write_poses(folder / "poses.txt", poses)
    return poses


def test_sequence_figure_and_its_path(tmp_path, capsys):
    poses = write_sequence(tmp_path / "seq")
    png = tmp_path / "out" / "sequence.png"
    assert main(["show", str(tmp_path / "seq"), "--png", str(png), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["frames"] == 3 and stats["points"] == [500, 500, 500]
    assert stats["path_m"] == pytest.approx(3.0, abs=1e-4)  # two steps of 1.5 m
    np.testing.assert_allclose(stats["last_position_m"], poses[-1, :3, 3], atol=1e-3)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sequence_folder_without_poses_is_named(tmp_path, capsys):
    write_sequence(tmp_path / "seq")
    (tmp_path / "seq" / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")  # one pose for three scans
    assert main(["show", str(tmp_path / "seq"), "--png", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "poses.txt" in err and "need frame 2" in err and "Traceback" not in err
    assert main(["show", str(tmp_path / "seq"), "--ply", str(tmp_path / "x.ply")]) == 2
    assert "--ply exports one scan" in capsys.readouterr().err


@pytest.mark.real
def test_real_kitti_sequence(kitti_root, tmp_path, capsys):
    sequence = kitti_root / "sequences" / "00"
    assert main(["show", str(sequence), "--png", str(tmp_path / "seq00.png"), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    # seq 00 frames 0-5 (SemanticKITTI poses): the car drives 3.55 m straight ahead
    assert stats["frames"] == 6 and min(stats["points"]) > 120_000
    assert 3.4 < stats["path_m"] < 3.7 and abs(stats["last_position_m"][1]) < 0.2
