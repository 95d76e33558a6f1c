"""The `u4d` command (u4d_aug/cli.py): help lists every command, info/show on real scans, one-line errors for bad
input."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from tests.tiny_nets import REPO
from u4d_aug.cli import CONFIGS_DIR, DELEGATED, EXAMPLES, PROGRESS_COMMANDS, main
from u4d_aug.data.formats import read_kitti_scan, read_poses
from u4d_aug.demo import sequence_motion
from u4d_aug.trajectory import poses_from_motion


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


def test_info_counts_all_ignore_label_files_apart(kitti_root, tmp_path, capsys):
    """A label file of only 0 (unlabeled), as `u4d export` writes for generated scans, is no labeled scan."""
    real = kitti_root / "sequences" / "00"
    root = tmp_path / "root"
    for folder in ("velodyne", "labels"):
        (root / "sequences" / "00" / folder).mkdir(parents=True)
    for frame in ("000000", "000001"):
        (root / "sequences" / "00" / "velodyne" / f"{frame}.bin").write_bytes(
            (real / "velodyne" / f"{frame}.bin").read_bytes()
        )
    (root / "sequences" / "00" / "labels" / "000000.label").write_bytes((real / "labels" / "000000.label").read_bytes())
    np.zeros(124_605, np.uint32).tofile(root / "sequences" / "00" / "labels" / "000001.label")  # all unlabeled
    assert main(["info", str(root), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["format"], summary["frames"], summary["labeled_frames"], summary["all_ignore_frames"]) == (
        "semantickitti", 2, 1, 1)  # fmt: skip
    assert summary["sequences"] == [{"sequence": "00", "frames": 2, "labeled_frames": 1, "all_ignore_frames": 1}]
    assert summary["class_histogram"]["road"] == 34228 + 1053  # the labeled scan's alone
    assert sum(summary["class_histogram"].values()) == 124_668
    assert main(["info", str(root)]) == 0
    table = capsys.readouterr().out
    assert "sequence 00: 2 frames, 1 labeled, 1 all-ignore" in table
    assert "labels: 2 scans, 1 of them all-ignore (not counted as labeled)" in table


def test_info_detects_the_layout_of_its_root(real_root, capsys):
    nuscenes = real_root / "nuscenes_mmdet3d_demo"
    if not nuscenes.is_dir():
        pytest.skip(f"{nuscenes}: real nuScenes sample not found")
    assert main(["info", str(nuscenes)]) == 2  # read as nuScenes: samples/LIDAR_TOP/, but no v1.0 tables to index it
    assert capsys.readouterr().err.strip() == (
        f"error: {nuscenes / 'v1.0-trainval'}: nuScenes table folder not found (expected ROOT/v1.0-*/*.json)"
    )
    assert main(["info", str(real_root)]) == 2  # the folder of the datasets: neither layout
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {real_root}: no dataset layout: looked for sequences/") and "\n" not in err
    assert main(["info", str(real_root / "semantickitti"), "--format", "semantickitti", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["format"] == "semantickitti"


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
    for name in ["generated.png", "u4d/checkpoints", "baseline/checkpoints"]:  # U4D: one net for both stages
        assert (out / name).exists(), name
    disjoint = np.sqrt(np.log(2))  # the JS distance of BEV histograms with disjoint supports
    for method in ["u4d", "baseline"]:
        bank = out / f"bank_{method}"
        manifest = json.loads((bank / "manifest.json").read_text())
        assert manifest["mode"] == method and manifest["complete"] and len(manifest["samples"]) == 8
        assert (manifest["height"], manifest["width"]) == (64, 1024) and manifest["empty"] == []  # the shipped nets
        written = sorted((bank / "sequences" / "00" / "velodyne").glob("*.bin"))
        assert len(written) == 8
        counts = [len(read_kitti_scan(path)) for path in written]  # measured 50k-60k of 65,536 pixels
        assert all(30_000 <= count <= 65_536 for count in counts), counts
        # BEV JS distance to the 30 scans of the demo world: measured 0.32 (U4D) and 0.27 (baseline), the
        # seconds-trained nets' banks gave 0.50; disjoint supports give 0.83
        table = json.loads((out / f"eval_{method}" / "evaluation.json").read_text())["table1"]
        assert 0.1 < table["jsd"]["value"] < 0.55 * disjoint, (method, table["jsd"])
        assert table["frd"]["value"] > 0 and table["frd"]["extractor_hash"] == "8952f78731a3fb61"
        assert table["fpd"]["value"] > 0 and table["fpd"]["extractor_hash"] == "ea1993e763a7ffc3"
    # the same command on identical inputs (a bank against itself) gives 0
    same = out / "eval_same"
    assert main(["evaluate", "--bank", str(out / "bank_u4d"), "--real", str(out / "bank_u4d"), "--metrics", "jsd",
                 "--json", "--out", str(same)]) == 0  # fmt: skip
    assert json.loads((same / "evaluation.json").read_text())["table1"]["jsd"]["value"] == pytest.approx(0.0, abs=1e-9)
    # the downstream comparison at toy size: every arm trained and scored on sequence 02, the banks really mixed in
    results = json.loads((out / "downstream" / "results.json").read_text())
    arms = {e["arm"]: e for e in results["arms"]}
    assert set(arms) == {"sup-only", "mt", "mt+baseline", "mt+u4d", "mt+real"}
    assert all(e["status"] == "done" and 0.02 < e["miou"]["mean"] < 1 for e in arms.values())
    assert arms["mt+u4d"]["bank"] == str(out / "bank_u4d") and arms["mt+baseline"]["bank"] == str(out / "bank_baseline")
    assert arms["mt+u4d"]["miou"]["mean"] != arms["mt"]["miou"]["mean"]  # the bank's scans changed the training
    assert [(c["arm"], c["reference"]) for c in results["contrasts"]] == [
        ("mt+u4d", "mt"),
        ("mt+u4d", "mt+baseline"),
        ("mt+real", "mt"),
    ]
    # the ceiling's bank: as many real scans as a generated bank, of the places 03-04 no split uses, at 64 x 1024
    real = json.loads((out / "bank_real" / "manifest.json").read_text())
    assert real["mode"] == "real" and real["complete"] and len(real["samples"]) == 8
    assert {s["source"].split("/")[1] for s in real["samples"]} <= {"03", "04"} and real["projection"]["width"] == 1024
    assert arms["mt+real"]["bank"] == str(out / "bank_real")
    assert "## Contrasts (points)" in (out / "downstream" / "results.md").read_text()
    # 4D: one sequence from the shipped MoST nets along the demo's drive, written with exactly those poses; its frames
    # follow them (TTCE-global k = 3 measured 0.052 m; static frames score ~1.7 m: temporal_follow_global_s1.md)
    manifest = json.loads((out / "bank_4d" / "manifest.json").read_text())
    assert manifest["complete"] and manifest["frames"] == 5 and manifest["sampling"]["propagate"] is True
    written = read_poses(out / "bank_4d" / "sequences" / "00" / "poses.txt")
    np.testing.assert_allclose(written, poses_from_motion(sequence_motion()), atol=1e-5)
    temporal = json.loads((out / "eval_4d" / "evaluation.json").read_text())["table2"]
    assert temporal["bank"]["ttce_global"]["3"] < 0.5 and temporal["real"]["ttce_global"]["3"] < 0.5, temporal
    assert (out / "sequence_4d.png").is_file()
    # the report: both tables with the measured numbers, the figures it links exist, a wall time per step
    report = (out / "report.md").read_text()
    assert "**Toy scale.**" in report and "benchmarks/results/downstream/" in report
    u4d_row = next(line for line in report.splitlines() if line.startswith("| u4d | 8 | 30 |"))
    assert f"{json.loads((out / 'eval_u4d' / 'evaluation.json').read_text())['table1']['jsd']['value']:.3f}" in u4d_row
    for arm in ("sup-only", "mt", "mt+baseline", "mt+u4d", "mt+real"):
        row = next(line for line in report.splitlines() if line.startswith(f"| {arm} | done |"))
        assert f"{100 * arms[arm]['miou']['mean']:.2f}" in row
    linked = [line.split("](")[1].rstrip(")") for line in report.splitlines() if "](" in line]
    assert "generated.png" in linked and all((out / name).is_file() for name in linked)
    step_rows = [line for line in report.split("## Wall time")[1].splitlines() if re.match(r"\| \d+ \| ", line)]
    printed = [line for line in capsys.readouterr().out.splitlines() if re.match(r"\[\d+/\d+\] ", line)]
    assert len(step_rows) == len(printed) >= 19 and "downstream, toy size" in step_rows[-1]
    assert "| generated (U4D+MoST, propagated) | " in report and "sequence_4d.png" in linked


# ---------------------------------------------------------------------------------------------------- conventions

COMMANDS = ["info", "show", "demo", *dict(DELEGATED)]


@pytest.mark.parametrize("name", COMMANDS)
def test_help_of_every_command_shows_an_example(name, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([name, "--help"])
    assert exit_info.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line for line in lines if line.startswith(f"example: u4d {name} ")] == [f"example: {EXAMPLES[name]}"]
    assert "--quiet" in "\n".join(lines)


def config_class(name: str) -> type | None:
    """The config dataclass a command reads its CONFIG (or bare overrides) with."""
    from segmentation.config import SegTrainConfig
    from segmentation.experiment import ExperimentConfig
    from u4d_aug.data.sim.config import SimConfig
    from u4d_aug.generate import GenerateConfig
    from u4d_aug.metrics.extractors import ExtractorConfig
    from u4d_aug.train import DiffusionTrainConfig

    classes = {"seg-train": SegTrainConfig, "train-diffusion": DiffusionTrainConfig, "generate": GenerateConfig,
               "experiment": ExperimentConfig, "train-extractor": ExtractorConfig, "simulate": SimConfig}  # fmt: skip
    return classes.get(name)


@pytest.mark.parametrize("name", COMMANDS)
def test_every_example_parses_and_its_overrides_load(name, tmp_path, monkeypatch):
    from u4d_aug.cli import build_parser, delegated_parser
    from u4d_aug.cmdline import parse_command_line
    from u4d_aug.config import load_config
    from u4d_aug.train import split_stage_override

    monkeypatch.chdir(tmp_path)  # presets are found from any folder
    words = shlex.split(EXAMPLES[name])
    assert words[:2] == ["u4d", name]
    if name in dict(DELEGATED):
        args = parse_command_line(delegated_parser(name)[0], words[2:])
    else:
        args = build_parser().parse_args(words[1:])
    cls = config_class(name)
    if cls is not None:
        overrides = split_stage_override(args.overrides) if name == "train-diffusion" else args.overrides
        assert overrides, "the example shows a key=value override"
        load_config(cls, getattr(args, "preset", None) or getattr(args, "config", None), overrides)


@pytest.mark.parametrize("name", [*PROGRESS_COMMANDS, "demo"])
def test_every_long_command_takes_no_progress(name):
    from u4d_aug.cli import build_parser, delegated_parser
    from u4d_aug.cmdline import parse_command_line

    words = [*shlex.split(EXAMPLES[name])[2:], "--no-progress"]
    if name in dict(DELEGATED):
        assert parse_command_line(delegated_parser(name)[0], words).no_progress is True
    else:
        assert build_parser().parse_args([name, *words]).no_progress is True


def test_every_command_module_that_draws_progress_bars_is_a_progress_command():
    """A new long command (its module calls progress_bar) must take --no-progress and be passed it by the demo."""
    import importlib

    from u4d_aug.cli import _delegated_command

    for name in dict(DELEGATED):
        module = importlib.import_module(_delegated_command(name)[1].__module__)
        if hasattr(module, "progress_bar"):
            assert name in PROGRESS_COMMANDS, name


def test_overrides_after_flags_reach_the_config(tmp_path, capsys):
    missing = tmp_path / "missing.pt"
    argv = ["generate", "u4d/generate_cpu", "--out", str(tmp_path / "bank"), "mode=baseline", f"baseline={missing}"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: {missing}: baseline checkpoint not found"


def test_a_shipped_weights_path_from_another_folder_finds_the_checkouts_file(tmp_path, monkeypatch):
    from u4d_aug.config import load_config
    from u4d_aug.generate import GenerateConfig, _checkpoint_paths
    from u4d_aug.presets import resolve_config_path

    monkeypatch.chdir(tmp_path)  # configs/u4d/generate_hdl64.yaml names weights/*.pt (u4d_aug.weights_store)
    cfg = load_config(GenerateConfig, resolve_config_path("u4d/generate_hdl64"), [])
    one_net = REPO / "weights" / "u4d.pt"  # the shipped U4D: one net for both stages
    assert _checkpoint_paths(cfg) == {"stage1": one_net, "stage2": one_net}


def test_unknown_flag_is_still_refused_in_one_line(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["seg-train", "seg/tiny", "optim.steps=1", "--bogus"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unrecognized arguments: --bogus" in err


def test_quiet_and_verbose_anywhere(tmp_path, capsys):
    (tmp_path / "sequences" / "00" / "velodyne").mkdir(parents=True)
    np.zeros((3, 4), np.float32).tofile(tmp_path / "sequences" / "00" / "velodyne" / "000000.bin")
    assert main(["info", str(tmp_path), "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 1
    assert main(["--verbose", "info", str(tmp_path)]) == 0


def test_one_launch_path_no_command_module_is_a_script_of_its_own():
    """`u4d COMMAND`, or `torchrun ... -m u4d_aug.cli COMMAND` for several processes: the modules behind the commands
    have no `main` and no `__main__` block of their own (they used to, one launch path each)."""
    import ast
    import importlib

    for name in ("u4d_aug.train", "u4d_aug.generate", "segmentation.train", "segmentation.evaluate",
                 "segmentation.predict", "segmentation.experiment"):  # fmt: skip
        module = importlib.import_module(name)
        tree = ast.parse(Path(module.__file__).read_text(encoding="utf-8"))
        blocks = [node for node in tree.body if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)]
        assert not hasattr(module, "main") and not blocks, name
    assert "__main__" in Path(importlib.import_module("u4d_aug.cli").__file__).read_text(encoding="utf-8")
