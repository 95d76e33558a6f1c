"""benchmarks/metric_validity.py: the verdict of one metric on hand-made values, the corruption check monotone on a
tiny ray-cast scene (the structure metrics, no nets), the script on a toy root, bad input in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.tiny_nets import load_script
from tests.tiny_worlds import write_toy_root
from tests.u4d_aug.metrics.test_corruptions import scene
from u4d_aug.metrics.corruptions import CORRUPTIONS, corrupt

validity = load_script("metric_validity")
bench = load_script("bench_generation")
STRUCTURE_KEYS = ["bev_points_per_cell", "ring_roughness", "vertical_roughness"]
GEOMETRY = {"sensor": "hdl64", "height": 64, "width": 1024, "row_mode": "beam"}


def test_a_metric_sees_a_corruption_when_it_moves_its_way_by_more_than_the_noise() -> None:
    assert validity.check([1.0, 2.0, 3.0], 0.5, 1) == {"rise": 2.0, "noise": 0.5, "monotone": True, "verdict": "sees"}
    assert validity.check([3.0, 2.0, 1.0], 0.5, -1)["verdict"] == "sees"  # a share that falls
    back = validity.check([1.0, 2.0, 1.8], 0.5, 1)  # sees it, but the last step goes back
    assert back["rise"] == pytest.approx(0.8) and back["verdict"] == "sees" and not back["monotone"]
    assert validity.check([1.0, 1.4, 1.2], 0.5, 1)["verdict"] == "cannot see"
    assert validity.check([1.0, 0.2], 0.5, 1)["verdict"] == "wrong way"
    assert validity.check([1.0, None], 0.5, 1)["verdict"] is None
    assert validity.SIGN["bev_points_per_cell"] == validity.SIGN["teacher_kept_share"] == -1
    assert validity.SIGN["frd"] == validity.SIGN["ring_roughness"] == 1


def _jittered(points: np.ndarray, seed: int) -> np.ndarray:
    """The scene as a sensor sees it on another sweep: every range off by N(0, 2 cm)."""
    ranges = np.linalg.norm(points[:, :3].astype(np.float64), axis=1, keepdims=True)
    factor = 1.0 + np.random.default_rng(seed).normal(0.0, 0.02, ranges.shape) / ranges
    return np.concatenate([points[:, :3] * factor, points[:, 3:]], 1).astype(np.float32)


def _structure(scan: np.ndarray) -> dict:
    """The benchmark's cheap metrics of one scan: BEV density and roughness (`bench_generation.structure_scores`)."""
    return bench.structure_scores([scan], ("bev_density", "roughness"), GEOMETRY)


def test_the_corruption_check_is_monotone_on_a_tiny_synthetic_case() -> None:
    clean = _jittered(scene()[0], 0)
    # the other draws, as the benchmark's are other scans: the same street with its walls 1 m nearer and farther
    draws = [_structure(_jittered(scene(wall_y)[0], seed)) for seed, wall_y in ((1, 7.0), (2, 9.0))]
    rows = {"clean": _structure(clean), "draws": draws, "kinds": {}}
    for index, kind in enumerate(CORRUPTIONS):
        rows["kinds"][kind] = {"0": rows["clean"]}
        for level in (0.25, 0.5, 1.0):
            rng = np.random.default_rng([0, index])
            rows["kinds"][kind][f"{level:g}"] = _structure(corrupt(clean, kind, level, rng))
    noise, checks = validity.checks_of(rows, STRUCTURE_KEYS)
    for kind in ("depth_noise", "smeared_walls"):  # every structure metric sees a scan that scatters along its rays
        for key in STRUCTURE_KEYS:
            assert checks[kind][key]["verdict"] == "sees" and checks[kind][key]["monotone"], (kind, key)
    dropped, swapped = checks["dropped_rows"], checks["swapped_columns"]
    assert dropped["bev_points_per_cell"]["verdict"] == "sees" and dropped["bev_points_per_cell"]["monotone"]
    assert swapped["ring_roughness"]["verdict"] == "sees" and swapped["ring_roughness"]["monotone"]
    # a wall's columns scattered over other azimuths no longer stack in its cells; the drop saturates once about half
    # of the columns have moved, so the density is not monotone up to level 1
    assert swapped["bev_points_per_cell"]["verdict"] == "sees"
    # blind spots: each kept ring is the ring it was, only the mix of rings changes (ring roughness cannot see dropped
    # rows); each column moves whole (vertical roughness cannot see swapped columns: it does not move at all)
    assert dropped["ring_roughness"]["verdict"] == "cannot see"
    assert swapped["vertical_roughness"]["verdict"] == "cannot see"
    assert abs(swapped["vertical_roughness"]["rise"]) < 1e-6 < noise["vertical_roughness"]


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """A toy root of 4 sequences x 3 scans."""
    return write_toy_root(tmp_path_factory.mktemp("validity") / "root", sequences=("00", "01", "02", "03"), frames=3)


def test_main_on_a_toy_root_writes_the_values_and_the_verdicts(root, tmp_path) -> None:
    work, out = tmp_path / "work", tmp_path / "out" / "validity.json"
    argv = ["--real", str(root), "--real-sequences", "00-01", "--num", "3", "--levels", "1", "--noise-draws", "1",
            "--metrics", "bev_density,roughness", "--work", str(work), "--out", str(out)]  # fmt: skip
    assert validity.main(argv) == 0
    result = json.loads(out.read_text())
    assert result["floor_sequences"] == ["02", "03"] and result["levels"] == [0.0, 1.0]
    assert result["keys"] == STRUCTURE_KEYS and result["sign"] == {key: validity.SIGN[key] for key in STRUCTURE_KEYS}
    assert list(result["rows"]["kinds"]) == list(CORRUPTIONS) and len(result["rows"]["draws"]) == 1
    for kind, levels in result["rows"]["kinds"].items():
        assert list(levels) == ["0", "1"] and levels["0"] == result["rows"]["clean"]
        assert len(list((work / f"{kind}_1_n3_s0" / "sequences" / "00" / "velodyne").glob("*.bin"))) == 3
    swapped = result["checks"]["swapped_columns"]["vertical_roughness"]
    assert swapped["verdict"] == "cannot see" and abs(swapped["rise"]) < 1e-6  # columns move whole
    assert result["rows"]["reference"]["bev_points_per_cell"] > 0 and result["noise"]["ring_roughness"] >= 0
    text = out.with_suffix(".md").read_text()
    assert "| smeared_walls | 1 |" in text and "points/BEV cell ↓" in text and "ring roughness ↑" in text
    assert "## Which metric sees which corruption" in text and "vertical_roughness / swapped_columns" in text
    assert "python benchmarks/metric_validity.py --real" in text


def test_bad_input_is_one_line(root, tmp_path, capsys) -> None:
    base = ["--real", str(root), "--real-sequences", "00-01", "--out", str(tmp_path / "v.json")]
    cases = [(["--kinds", "stars"], "depth_noise, smeared_walls"), (["--levels", "1.5"], "[0, 1]"),
             (["--metrics", "points"], "no direction"), (["--metrics", "stars"], "bev_density"),
             (["--num", "0"], "--num")]  # fmt: skip
    for extra, named in cases:
        assert validity.main(base + extra + ["--work", str(tmp_path / "w")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and named in err and "\n" not in err, err
