"""The `u4d` command: help lists every command, info/show on real scans, one-line errors for bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from u4d_aug.cli import CONFIGS_DIR, DELEGATED, main


def test_help_lists_every_command(capsys):
    assert main([]) == 0
    text = capsys.readouterr().out
    for name in ["info", "show", "demo", *dict(DELEGATED)]:
        assert name in text


def test_info_on_real_root(kitti_root, capsys):
    assert main(["info", str(kitti_root), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 6 and summary["labeled_frames"] == 3
    assert summary["points_per_scan"]["max"] == 124668
    assert summary["class_histogram"]["road"] == 34228 + 1053 + 33233 + 868 + 32230 + 662


def test_show_real_scan_png_ply_and_stats(kitti_root, tmp_path, capsys):
    scan = kitti_root / "sequences" / "00" / "velodyne" / "000000.bin"
    png, ply = tmp_path / "s.png", tmp_path / "s.ply"
    assert main(["show", str(scan), "--width", "2048", "--png", str(png), "--ply", str(ply), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["points"] == 124668
    assert stats["kept_fraction"] >= 0.85
    assert stats["median_error_m"] <= 0.03
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import open3d as o3d

    assert len(o3d.io.read_point_cloud(str(ply)).points) == 124668


def test_bad_scan_size_is_one_line_error(tmp_path, capsys):
    bad = tmp_path / "velodyne" / "000000.bin"
    bad.parent.mkdir()
    bad.write_bytes(np.zeros(7, np.float32).tobytes())
    assert main(["show", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert str(bad) in err and "not a multiple of 16" in err


def test_missing_velodyne_folder(tmp_path, capsys):
    (tmp_path / "sequences" / "00").mkdir(parents=True)
    assert main(["info", str(tmp_path)]) == 2
    assert "error:" in capsys.readouterr().err


def test_unknown_config_key_through_seg_train(tmp_path, capsys):
    assert main(["seg-train", str(CONFIGS_DIR / "seg" / "tiny.yaml"), "optim.stepz=3", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown config key 'optim.stepz'" in err and "steps" in err


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo")]) == 0
    out = tmp_path / "demo"
    for name in ["frame0.png", "reliability.png", "seg/model.pt", "seg/log.jsonl", "probs/manifest.json"]:
        assert (out / name).is_file(), name
    assert len(list((out / "probs" / "sequences" / "00" / "probs").glob("*.npy"))) == 6
    for name in ["generated.png", "u4d_stage1/checkpoints", "u4d_stage2/checkpoints", "baseline/checkpoints"]:
        assert (out / name).exists(), name
    for method in ["u4d", "baseline"]:
        manifest = json.loads((out / f"bank_{method}" / "manifest.json").read_text())
        assert manifest["mode"] == method and manifest["complete"] and len(manifest["samples"]) == 4
        written = list((out / f"bank_{method}" / "sequences" / "00" / "velodyne").glob("*.bin"))
        assert len(written) + len(manifest["empty"]) == 4
        evaluation = json.loads((out / f"eval_{method}" / "evaluation.json").read_text())
        assert 0.0 <= evaluation["table1"]["jsd"]["value"] <= np.sqrt(np.log(2)) + 1e-9
