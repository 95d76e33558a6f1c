"""benchmarks/reports/transfer_table.py: the sim-to-real transfer table (real mIoU over present classes, ECE, sim mIoU
per world over seeds, seed-paired after - before with 95 % CI and p, the goals, per-class IoU, the summed real
confusion) from `u4d seg-eval --json` outputs; a world/seed without its json is listed, bad files in one line."""

from __future__ import annotations

import json
import math

import pytest
from scipy import stats

from tests.tiny_nets import load_script

table = load_script("reports/transfer_table")
CLASSES = ("car", "road", "bicycle")  # bicycle: no ground truth in the real scans
T_975_DF1 = 12.706204736174707  # Student t, 97.5 % quantile, 1 degree of freedom (tables)


def real_eval(miou: float, ece: float, car: float, road: float, confusion: list[list[int]]) -> dict:
    """An eval_real.json as `u4d seg-eval --json` writes it (fractions; ECE pooled = half the per-scan ECE)."""
    return {
        "miou": miou * 2 / 3,
        "miou_present": miou,
        "classes_present": ["car", "road"],
        "iou": {"car": car, "road": road, "bicycle": None},
        "ece_per_scan": ece,
        "ece_pooled": ece / 2,
        "num_scans": 40,
        "confusion": confusion,
        "bins": {},
        "bands": [],
        "checkpoint": "model.pt",
        "step": 1284,
    }


RICH = [[6, 2, 2], [1, 9, 0], [0, 0, 0]]  # rows = ground truth car, road, bicycle; columns = prediction
VARIED = [[8, 2, 0], [0, 9, 1], [0, 0, 0]]


def write_run(runs, name: str, real: dict | str | None, sim: float | None) -> None:
    """runs/NAME with eval_real.json (a dict, raw text, or none) and eval_sim.json (its mIoU, or none)."""
    folder = runs / name
    folder.mkdir(parents=True)
    if real is not None:
        (folder / "eval_real.json").write_text(real if isinstance(real, str) else json.dumps(real))
    if sim is not None:
        (folder / "eval_sim.json").write_text(json.dumps({"miou": sim, "iou": {}, "ece_per_scan": 0.01}))


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """seg_rich on seeds 0-2, varied on seeds 0-1 and a seed 2 whose real evaluation is missing: (out, json, md)."""
    root = tmp_path_factory.mktemp("transfer")
    runs = root / "runs"
    for seed, (miou, ece, car) in enumerate(((0.30, 0.10, 0.2), (0.34, 0.12, 0.4), (0.32, 0.08, 0.3))):
        write_run(runs, f"seg_rich_s{seed}", real_eval(miou, ece, car, 0.5, RICH), 0.8)
    for seed, (miou, ece, car, road) in enumerate(((0.50, 0.04, 0.6, 0.7), (0.56, 0.05, 0.4, 0.9))):
        write_run(runs, f"varied_s{seed}", real_eval(miou, ece, car, road, VARIED), (0.7, 0.9)[seed])
    write_run(runs, "varied_s2", None, 0.8)  # trained and scored on sim, the real evaluation not run yet
    (runs / "other_s7").mkdir()  # another world's run: not a seed of these worlds
    out = root / "results" / "sim_to_real_transfer"
    assert table.main(["--runs", str(runs), "--worlds", "seg_rich", "varied", "--out", str(out)]) == 0
    result = json.loads((root / "results" / "sim_to_real_transfer.json").read_text())
    return root, result, (root / "results" / "sim_to_real_transfer.md").read_text()


def test_worlds_in_percent_over_seeds_by_hand(written):
    _, result, _ = written
    assert (result["before"], result["after"], result["seeds"]) == ("seg_rich", "varied", [0, 1, 2])
    assert result["classes_present"] == ["car", "road"]
    rich, varied = result["worlds"]["seg_rich"], result["worlds"]["varied"]
    assert (rich["role"], varied["role"]) == ("before", "after")
    miou = rich["real"]["miou_present"]
    assert miou["per_seed"] == pytest.approx([30.0, 34.0, 32.0]) and miou["n"] == 3
    assert (miou["mean"], miou["std"]) == (pytest.approx(32.0), pytest.approx(2.0))  # ddof 1
    assert rich["real"]["ece_per_scan"]["mean"] == pytest.approx(10.0) and rich["real"]["ece_per_scan"][
        "std"
    ] == pytest.approx(2.0)
    assert rich["real"]["ece_pooled"]["mean"] == pytest.approx(5.0)
    assert rich["sim"]["miou"]["mean"] == pytest.approx(80.0) and rich["sim"]["miou"]["std"] == pytest.approx(0.0)
    assert rich["real"]["iou"] == pytest.approx({"car": 30.0, "road": 50.0})  # bicycle absent: no IoU
    # varied: seed 2 not measured on the real scans (null in per_seed), measured on sim
    assert varied["measured_real"] == [0, 1] and varied["measured_sim"] == [0, 1, 2]
    vm = varied["real"]["miou_present"]
    assert vm["per_seed"][:2] == pytest.approx([50.0, 56.0]) and vm["per_seed"][2] is None
    assert (vm["mean"], vm["std"], vm["n"]) == (pytest.approx(53.0), pytest.approx(3 * math.sqrt(2)), 2)
    assert varied["real"]["ece_per_scan"]["mean"] == pytest.approx(4.5)
    assert varied["sim"]["miou"]["per_seed"] == pytest.approx([70.0, 90.0, 80.0])
    assert (varied["sim"]["miou"]["mean"], varied["sim"]["miou"]["std"]) == (pytest.approx(80.0), pytest.approx(10.0))
    assert varied["real"]["iou"] == pytest.approx({"car": 50.0, "road": 80.0})


def test_confusion_summed_over_seeds_and_row_normalised(written):
    _, result, _ = written
    rich = result["worlds"]["seg_rich"]["real"]["confusion"]
    assert rich["rows"] == ["car", "road"] and rich["columns"] == ["car", "road", "other"]
    assert rich["points"] == [[18, 6, 6], [3, 27, 0]]  # 3 seeds; the bicycle column folded into "other"
    assert rich["percent"] == [pytest.approx([60.0, 20.0, 20.0]), pytest.approx([10.0, 90.0, 0.0])]
    varied = result["worlds"]["varied"]["real"]["confusion"]
    assert varied["points"] == [[16, 4, 0], [0, 18, 2]]
    assert varied["percent"] == [pytest.approx([80.0, 20.0, 0.0]), pytest.approx([0.0, 90.0, 10.0])]


def test_paired_after_minus_before_on_common_seeds(written):
    _, result, _ = written
    paired = result["paired"]["varied_vs_seg_rich"]
    miou = paired["miou_present"]  # seeds 0, 1: +20, +22 points
    assert miou["seeds"] == [0, 1] and miou["per_seed"] == pytest.approx([20.0, 22.0])
    assert (miou["mean"], miou["std"], miou["n"]) == (pytest.approx(21.0), pytest.approx(math.sqrt(2)), 2)
    half = T_975_DF1 * math.sqrt(2) / math.sqrt(2)
    assert miou["ci95"] == pytest.approx([21.0 - half, 21.0 + half])
    # paired t = 21 / (sqrt 2 / sqrt 2) = 21; one degree of freedom (Cauchy): p = 1 - 2 arctan(21) / pi
    assert miou["p"] == pytest.approx(1 - 2 * math.atan(21.0) / math.pi)
    assert miou["p"] == pytest.approx(stats.ttest_rel([50, 56], [30, 34]).pvalue)
    ece = paired["ece_per_scan"]
    assert ece["per_seed"] == pytest.approx([-6.0, -7.0]) and ece["mean"] == pytest.approx(-6.5)
    assert ece["std"] == pytest.approx(1 / math.sqrt(2))
    assert paired["unpaired_seeds"] == {"2": "only seg_rich measured"}


def test_missing_world_seed_is_listed_not_dropped(written):
    _, result, text = written
    assert result["missing"] == [
        {"world": "varied", "seed": 2, "file": result["missing"][0]["file"], "reason": "not found"}
    ]
    assert result["missing"][0]["file"].endswith("varied_s2/eval_real.json")
    assert "## Not measured" in text and "- varied seed 2: `" in text and "varied_s2/eval_real.json` not found" in text
    assert "left out: seed 2 (only seg_rich measured)" in text


def test_markdown_tables_goals_and_command(written):
    root, result, text = written
    assert result["command"].startswith("python benchmarks/reports/transfer_table.py --runs ")
    assert f"`{result['command']}`" in text
    assert "| seg_rich | before | 32.00 ± 2.00 | s0 30.00, s1 34.00, s2 32.00 | 10.00 ± 2.00 |" in text
    assert "| varied | after | 53.00 ± 4.24 | s0 50.00, s1 56.00, s2 - | 4.50 ± 0.71 |" in text
    assert "| real mIoU present (points) | 0, 1 | s0 +20.00, s1 +22.00 | +21.00 ± 1.41 | [+8.29, +33.71] |" in text
    assert (
        "- **real mIoU over present classes ≥ 50 %**: seg_rich (before) 32.00 %: not met (0 of 3 seeds); "
        "varied (after) 53.00 %: met (2 of 2 seeds)." in text
    )
    assert (
        "- **real ECE per scan ≤ 5 %**: seg_rich (before) 10.00 %: not met (0 of 3 seeds); varied (after) 4.50 %"
        in text
    )
    assert [g["worlds"]["varied"]["met"] for g in result["goals"]] == [True, True]
    # the per-class table: present classes only, mean over seeds, after - before
    assert "| class | seg_rich (before) % | varied (after) % | varied − seg_rich |" in text
    assert "| car | 30.00 | 50.00 | +20.00 |\n| road | 50.00 | 80.00 | +30.00 |\n" in text
    assert "| bicycle |" not in text


def test_confusion_png_written(written):
    root, result, text = written
    assert result["figures"]["confusion"] == "sim_to_real_transfer_confusion.png"
    png = (root / "results" / "sim_to_real_transfer_confusion.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 1000
    assert "![confusion](sim_to_real_transfer_confusion.png)" in text
    assert not list((root / "results").glob(".*.tmp"))  # atomic writes left no temp file


def test_seed_of_one_world_only_pairs_the_rest(tmp_path, capsys):
    runs = tmp_path / "runs"
    write_run(runs, "seg_rich_s0", real_eval(0.30, 0.10, 0.2, 0.5, RICH), 0.8)
    write_run(runs, "seg_rich_s1", real_eval(0.34, 0.12, 0.4, 0.5, RICH), 0.8)
    write_run(runs, "varied_s0", real_eval(0.50, 0.04, 0.6, 0.7, VARIED), 0.7)
    assert table.main(["--runs", str(runs), "--out", str(tmp_path / "t")]) == 0  # default worlds
    result = json.loads((tmp_path / "t.json").read_text())
    assert [(m["world"], m["seed"], m["reason"]) for m in result["missing"]] == [
        ("varied", 1, "no run folder"),
        ("varied", 1, "no run folder"),
    ]
    assert {m["file"].rsplit("/", 1)[1] for m in result["missing"]} == {"eval_real.json", "eval_sim.json"}
    varied = result["worlds"]["varied"]["real"]["miou_present"]
    assert varied["mean"] == pytest.approx(50.0) and varied["std"] is None  # one seed: no std
    miou = result["paired"]["varied_vs_seg_rich"]["miou_present"]
    assert miou["seeds"] == [0] and miou["mean"] == pytest.approx(20.0)
    assert miou["std"] is None and miou["ci95"] is None and miou["p"] is None
    text = (tmp_path / "t.md").read_text()
    assert "left out: seed 1 (only seg_rich measured)" in text and "Fewer than 2 paired seeds" in text
    assert "50.00 (1 seed)" in text
    assert "# Sim-to-real transfer" in capsys.readouterr().out  # the table is printed


@pytest.mark.parametrize(
    ("real", "message"),
    [
        ('{"miou_present": 0.3', "seg_rich_s0/eval_real.json: not valid json"),
        ({"miou": 0.3, "iou": {}}, "seg_rich_s0/eval_real.json: no key 'miou_present'"),
        ([1, 2], "seg_rich_s0/eval_real.json: expected a json object"),
        ({**real_eval(0.3, 0.1, 0.2, 0.5, RICH), "miou_present": "high"}, "eval_real.json: miou_present: expected a"),
        ({**real_eval(0.3, 0.1, 0.2, 0.5, RICH), "confusion": [[1, 2]]}, "eval_real.json: confusion: expected 3 x 3"),
        (
            {**real_eval(0.3, 0.1, 0.2, 0.5, RICH), "iou": {"road": 0.5, "car": 0.2, "bicycle": None}},
            "varied_s0/eval_real.json: classes ['car', 'road', 'bicycle'] differ",
        ),
    ],
)
def test_bad_json_is_one_line_naming_the_file(tmp_path, capsys, real, message):
    runs = tmp_path / "runs"
    write_run(runs, "varied_s0", real_eval(0.50, 0.04, 0.6, 0.7, VARIED), 0.7)  # seg_rich is read first
    write_run(runs, "seg_rich_s0", real, 0.8)
    assert table.main(["--runs", str(runs), "--out", str(tmp_path / "o" / "t")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and len(err.strip().splitlines()) == 1
    assert "Traceback" not in err and not (tmp_path / "o").exists()  # nothing written


def test_bad_sim_json_and_arguments(tmp_path, capsys):
    runs = tmp_path / "runs"
    write_run(runs, "seg_rich_s0", real_eval(0.30, 0.10, 0.2, 0.5, RICH), None)
    (runs / "seg_rich_s0" / "eval_sim.json").write_text(json.dumps({"iou": {}}))
    out = ["--out", str(tmp_path / "o" / "t")]
    assert table.main(["--runs", str(runs), *out]) == 2
    assert table.main(["--runs", str(runs), "--worlds", "seg_rich", *out]) == 2
    assert table.main(["--runs", str(runs), "--worlds", "a", "b", *out]) == 2
    assert table.main(["--runs", str(tmp_path / "nowhere"), *out]) == 2
    err = capsys.readouterr().err.splitlines()
    assert "seg_rich_s0/eval_sim.json: no key 'miou'" in err[0]
    assert "expected at least two distinct worlds" in err[1]
    assert "no run folder a_sN or b_sN" in err[2] and "nowhere: not a folder" in err[3]
    assert not (tmp_path / "o").exists()
