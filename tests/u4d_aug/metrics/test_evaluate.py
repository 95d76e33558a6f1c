"""`u4d evaluate`: Table 1/2 on real seq-00 frames (real vs real) and on tiny synthetic roots."""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import EXTRACTOR_TINY as TINY_CONFIG
from tests.tiny_worlds import write_tiny_root
from u4d_aug.config import load_config
from u4d_aug.errors import InputError
from u4d_aug.metrics.evaluate import (
    add_evaluate_arguments,
    evaluate,
    list_scans,
    parse_metrics,
    run_evaluate,
    to_markdown,
)
from u4d_aug.metrics.extractors import ExtractorConfig, compare_results, train_extractor


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A real-like root (labels, poses), a bank without labels or poses, and tiny FRD/FPD extractors."""
    torch.set_num_threads(1)
    base = tmp_path_factory.mktemp("evaluate")
    real = write_tiny_root(base / "real", num_frames=5)
    bank = write_tiny_root(base / "bank", num_frames=4, labels=False, poses=False, shift=1.5)
    out = {"real": real, "bank": bank}
    for seed in (0, 1):
        cfg = load_config(ExtractorConfig, TINY_CONFIG, [f"data.root={real}", f"out_dir={base / f's{seed}'}"])
        cfg.train.seed = seed
        for kind in ("frd", "fpd"):
            out[f"{kind}{seed}"] = train_extractor(kind, cfg)[0]
    return out


def test_real_vs_real_is_zero_and_temporal_is_small(kitti_root):
    result = evaluate(kitti_root, kitti_root, ("jsd", "mmd", "ttce", "ttce_global", "ctc"), max_scans=5)
    assert result["counts"] == {"bank": 5, "real": 5}
    assert result["table1"]["jsd"]["value"] == pytest.approx(0.0, abs=1e-12)
    assert result["table1"]["mmd"]["value"] == pytest.approx(0.0, abs=1e-9)
    bank = result["table2"]["bank"]
    # ICP recovers the ground-truth motion of the real sequence: TTCE 0.018 / 0.009 m on frames 0-5
    assert set(bank["ttce"]) == {"3", "4"} and all(v < 0.05 for v in bank["ttce"].values())
    assert bank["ttce_pairs"] == {"3": 2, "4": 1}
    assert all(v < 0.05 for v in bank["ttce_global"].values()) and bank["ttce_global_pairs"] == {"3": 2, "4": 1}
    # consecutive real frames are not identical, so the chamfer grows with the interval (m^2)
    ctc = [bank["ctc"][k] for k in "1234"]
    assert 0.0 < ctc[0] < ctc[3]
    text = to_markdown(result)
    assert "Table 1" in text and "Table 2" in text and "TTCE k=3" in text and "(5 scans)" in text
    assert "TTCE-global k=4 (m)" in text


def test_synthetic_bank_tables_hashes_and_missing_poses(synthetic):
    result = evaluate(
        synthetic["bank"], synthetic["real"], extractor_frd=synthetic["frd0"], extractor_fpd=synthetic["fpd0"]
    )
    table1 = result["table1"]
    assert set(table1) == {"frd", "fpd", "jsd", "mmd", "points", "rangejs", "intensityjs"}
    assert len(table1["frd"]["extractor_hash"]) == 16 and len(table1["fpd"]["extractor_hash"]) == 16
    assert table1["frd"]["feature_dim"] == 4096 and table1["fpd"]["feature_dim"] == 56
    assert table1["frd"]["value"] > 0 and table1["jsd"]["value"] > 0 and table1["mmd"]["value"] > 0
    assert "poses.txt not found" in result["table2"]["bank"]["missing"]
    assert "ttce" in result["table2"]["real"]
    text = to_markdown(result)
    assert "bank temporal metrics missing" in text and table1["frd"]["extractor_hash"] in text


def test_frd_real_vs_itself_is_zero(synthetic):
    result = evaluate(
        synthetic["real"],
        synthetic["real"],
        ("frd", "fpd"),
        extractor_frd=synthetic["frd0"],
        extractor_fpd=synthetic["fpd0"],
    )
    assert abs(result["table1"]["frd"]["value"]) < 1e-6
    assert abs(result["table1"]["fpd"]["value"]) < 1e-6
    assert result["table2"] == {}


def test_results_with_other_extractors_are_not_compared(synthetic):
    a = evaluate(synthetic["bank"], synthetic["real"], ("frd",), extractor_frd=synthetic["frd0"])
    b = evaluate(synthetic["bank"], synthetic["real"], ("frd",), extractor_frd=synthetic["frd1"])
    assert compare_results(a, a) == {"frd": 0.0}
    with pytest.raises(InputError, match="extractor"):
        compare_results(a, b)


def test_missing_extractor_and_wrong_kind(synthetic):
    result = evaluate(synthetic["bank"], synthetic["real"], ("frd", "jsd"))
    assert result["table1"]["frd"]["value"] is None and "--extractor-frd" in result["table1"]["frd"]["missing"]
    with pytest.raises(InputError, match="fpd extractor"):
        evaluate(synthetic["bank"], synthetic["real"], ("frd",), extractor_frd=synthetic["fpd0"])


def test_cli_writes_json_and_md(synthetic, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_evaluate_arguments(parser)
    args = parser.parse_args(
        ["--bank", str(synthetic["bank"]), "--real", str(synthetic["real"]), "--metrics", "jsd,mmd,ctc"]
        + ["--json", "--md", "--out", str(tmp_path / "o"), "--max-scans", "3"]
    )
    assert run_evaluate(args) == 0
    printed = capsys.readouterr().out
    data = json.loads((tmp_path / "o" / "evaluation.json").read_text())
    assert data["counts"] == {"bank": 3, "real": 3} and data["config"]["max_scans"] == 3
    assert set(data["table2"]["real"]["ctc"]) == {"1", "2", "3", "4"}
    assert data["table2"]["real"]["ctc"]["3"] is None  # 3 scans have no pair 3 frames apart: NaN -> null
    assert data["table2"]["real"]["ctc_pairs"] == {"1": 2, "2": 1, "3": 0, "4": 0}
    assert (tmp_path / "o" / "evaluation.md").read_text() + "\n" == printed


@pytest.mark.parametrize("quiet", [False, True])
def test_cli_shows_progress_over_each_pass_unless_told_not_to(synthetic, tmp_path, capsys, quiet):
    parser = argparse.ArgumentParser()
    add_evaluate_arguments(parser)
    argv = ["--bank", str(synthetic["bank"]), "--real", str(synthetic["real"]), "--metrics", "points,jsd,ctc"]
    args = parser.parse_args(argv + ["--max-scans", "3"] + (["--no-progress"] if quiet else []))
    assert run_evaluate(args) == 0
    err = capsys.readouterr().err
    for what in ("BEV bank", "BEV real", "statistics bank", "statistics real", "temporal real"):
        assert (what in err) != quiet, what


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="--metrics"):
        parse_metrics("jsd,fid")
    assert parse_metrics("JSD, mmd,jsd") == ("jsd", "mmd")
    with pytest.raises(InputError, match="sequences"):
        list_scans(tmp_path)
    root = write_tiny_root(tmp_path / "r", num_frames=2, labels=False, poses=False)
    with pytest.raises(InputError, match="max-scans"):
        list_scans(root, 0)
    assert len(list_scans(Path(root), 1)) == 1
    assert [seq for seq, _, _ in list_scans(root, None, ["00"])] == ["00", "00"]
    with pytest.raises(InputError, match="sequence.*07 not found; present: 00"):
        list_scans(root, None, ["07"])
    assert [seq for seq, _, _ in list_scans(root, None, ["00-00"])] == ["00", "00"]  # ranges as in configs
    with pytest.raises(InputError, match="sequence.*01 not found; present: 00"):
        list_scans(root, None, ["00-01"])


def write_scans(root: Path, scans: list) -> Path:
    from u4d_aug.data.formats import write_kitti_scan

    for i, points in enumerate(scans):
        write_kitti_scan(root / "sequences" / "00" / "velodyne" / f"{i:06d}.bin", points)
    return root


def ring(count: int, radius: float) -> np.ndarray:
    angle = np.linspace(0, 2 * np.pi, count, endpoint=False)
    return np.stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(count), np.ones(count)], 1).astype(
        np.float32
    )


def test_points_per_scan_and_range_histogram_js(tmp_path):
    """Hand-made scans: rings of known size and radius give known counts and range pmfs."""
    import math

    real = write_scans(tmp_path / "real", [ring(100, 10.5), ring(300, 20.5)])  # 200 points/scan, a quarter at 10 m
    same = write_scans(tmp_path / "same", [ring(300, 20.5), ring(100, 10.5)])  # the same pooled pmf of ranges
    far = write_scans(tmp_path / "far", [ring(50, 30.5)])  # 50 points, all at 30 m
    result = evaluate(same, real, ("points", "rangejs"))["table1"]
    assert result["points"]["value"] == 200 and result["points"]["real"] == 200
    assert result["points"]["ratio_to_real"] == 1.0 and result["rangejs"]["value"] == pytest.approx(0.0, abs=1e-9)
    result = evaluate(far, real, ("points", "rangejs"))["table1"]
    assert result["points"]["value"] == 50 and result["points"]["ratio_to_real"] == 0.25
    assert result["rangejs"]["value"] == pytest.approx(math.sqrt(math.log(2)), rel=1e-6)  # disjoint supports
    mixed = write_scans(tmp_path / "mixed", [ring(100, 10.5), ring(100, 30.5)])
    p, q = np.array([0.25, 0.75, 0.0]), np.array([0.5, 0.0, 0.5])  # pmfs over 10 / 20 / 30 m
    m = (p + q) / 2
    kl = lambda a, b: sum(x * math.log(x / y) for x, y in zip(a, b) if x > 0)  # noqa: E731
    expected = math.sqrt((kl(p, m) + kl(q, m)) / 2)
    assert evaluate(mixed, real, ("rangejs",))["table1"]["rangejs"]["value"] == pytest.approx(expected, rel=1e-6)


def test_intensity_histogram_js_and_means(tmp_path):
    """Hand-made intensities: the same pooled pmf scores 0, disjoint bins sqrt(ln 2), and each side's mean is kept."""
    import math

    def with_intensity(count: int, value: float) -> np.ndarray:
        scan = ring(count, 10.5)
        scan[:, 3] = value
        return scan

    real = write_scans(tmp_path / "real", [with_intensity(100, 0.01), with_intensity(100, 0.99)])  # bins 0 and 49
    same = write_scans(tmp_path / "same", [np.concatenate([with_intensity(50, 0.01), with_intensity(50, 0.99)])])
    mid = write_scans(tmp_path / "mid", [with_intensity(80, 0.5)])
    above = write_scans(tmp_path / "above", [with_intensity(40, 3.0)])  # outside [0, 1]: counted in the last bin
    assert evaluate(same, real, ("intensityjs",))["table1"]["intensityjs"]["value"] == pytest.approx(0.0, abs=1e-9)
    entry = evaluate(mid, real, ("intensityjs",))["table1"]["intensityjs"]
    assert entry["value"] == pytest.approx(math.sqrt(math.log(2)), rel=1e-6)  # disjoint supports
    assert entry["mean"] == pytest.approx(0.51) and entry["real_mean"] == pytest.approx(0.5)  # bin centres
    p, q = np.array([0.5, 0.5]), np.array([0.0, 1.0])  # pmfs over bins 0 / 49
    m = (p + q) / 2
    kl = lambda a, b: sum(x * math.log(x / y) for x, y in zip(a, b) if x > 0)  # noqa: E731
    expected = math.sqrt((kl(p, m) + kl(q, m)) / 2)
    with warnings.catch_warnings():  # the reader warns of the odd scale (once per process: not asserted here)
        warnings.simplefilter("ignore", UserWarning)
        assert evaluate(above, real, ("intensityjs",))["table1"]["intensityjs"]["value"] == pytest.approx(expected)


def test_a_bank_with_placeholder_poses_has_no_temporal_metrics(kitti_root, tmp_path):
    """A single-frame bank's identity poses.txt (u4d_aug.bank: "placeholder_poses") are no ground truth for TTCE/CTC."""
    import shutil

    from u4d_aug.bank import write_manifest

    bank = tmp_path / "bank"
    shutil.copytree(kitti_root, bank)  # real poses.txt / calib.txt, but the manifest says they are placeholders
    write_manifest(bank, {"mode": "u4d", "frames": 1, "samples": [], "complete": True, "placeholder_poses": True})
    result = evaluate(bank, kitti_root, ("ttce", "ctc"), max_scans=5)
    assert "identity placeholders" in result["table2"]["bank"]["missing"]
    assert "ttce" in result["table2"]["real"]
