"""benchmarks/reports/temporal_table.py: Table 2 (TTCE k=3,4, CTC k=1..4, FRD) mean ± std over seeds and the MoST fusion
ablation from `u4d evaluate` evaluation.json files; missing entries keep their reason; bad input in one line."""

from __future__ import annotations

import json
import math

import pytest

from tests.tiny_nets import load_script

table = load_script("reports/temporal_table")


def evaluation(ttce3: float, ctc1: float, frd: float | None = 1.0, missing: str | None = None) -> dict:
    """An evaluation.json as `u4d evaluate` writes it: TTCE k=4 = ttce3 + 1, CTC k = ctc1 * k; real side fixed."""
    bank = (
        {"missing": missing}
        if missing
        else {
            "sequences": ["00"],
            "scans": 10,
            "ttce": {"3": ttce3, "4": ttce3 + 1},
            "ctc": {str(k): ctc1 * k for k in range(1, 5)},
            "ttce_pairs": {"3": 7, "4": 6},
            "ctc_pairs": {str(k): 10 - k for k in range(1, 5)},
        }
    )
    table1 = {"frd": {"value": frd} if frd is not None else {"value": None, "missing": "no extractor given"}}
    return {"bank": "b", "real": "r", "table1": table1, "table2": {"bank": bank, "real": {"missing": "unused"}}}


def write(folder, result) -> str:
    """`result` as folder/evaluation.json; returns the folder as a string."""
    folder.mkdir(parents=True)
    (folder / "evaluation.json").write_text(result if isinstance(result, str) else json.dumps(result))
    return str(folder)


@pytest.fixture
def runs(tmp_path):
    """u4d_most on 2 seeds, floor on 2 seeds, u4d_no_temporal missing, fusion gating (2 seeds) and add (1 seed)."""
    return {
        "u4d_most": [
            write(tmp_path / "m0", evaluation(0.2, 0.1, 10.0)),
            write(tmp_path / "m1", evaluation(0.4, 0.3, 14.0)),
        ],
        "floor": [write(tmp_path / "f0", evaluation(0.1, 0.01)), write(tmp_path / "f1", evaluation(0.1, 0.01))],
        "u4d_no_temporal": [write(tmp_path / "n0", evaluation(0, 0, None, missing="poses.txt not found"))],
        "gating": [write(tmp_path / "g0", evaluation(0.3, 0.2)), write(tmp_path / "g1", evaluation(0.5, 0.2))],
        "add": [write(tmp_path / "a0", evaluation(0.6, 0.5))],
    }


def argv(runs, out) -> list[str]:
    args = []
    for name in ("u4d_most", "floor", "u4d_no_temporal"):
        args += [a for d in runs[name] for a in ("--method", f"{name}={d}")]
    for name in ("gating", "add"):
        args += [a for d in runs[name] for a in ("--fusion", f"{name}={d}")]
    return [*args, "--out", str(out)]


def test_table_numbers_and_markdown(runs, tmp_path):
    out = tmp_path / "results" / "temporal"
    assert table.main(argv(runs, out)) == 0
    result = json.loads((tmp_path / "results" / "temporal.json").read_text())
    most = result["methods"]["u4d_most"]
    assert most["seeds"] == 2 and most["sources"] == [f"{d}/evaluation.json" for d in runs["u4d_most"]]
    sd = math.sqrt(0.02)  # two values d apart: sample std (ddof 1) = |d| / sqrt(2); d = 0.2
    assert most["ttce"]["3"]["mean"] == pytest.approx(0.3) and most["ttce"]["3"]["std"] == pytest.approx(sd)
    assert most["ttce"]["4"]["mean"] == pytest.approx(1.3) and most["ttce"]["3"]["n"] == 2
    assert most["ttce"]["3"]["per_seed"] == pytest.approx([0.2, 0.4])
    assert most["ctc"]["4"]["mean"] == pytest.approx(0.8) and most["ctc"]["4"]["std"] == pytest.approx(4 * sd)
    assert most["frd"]["mean"] == pytest.approx(12.0) and most["frd"]["std"] == pytest.approx(2 * math.sqrt(2))
    floor = result["methods"]["floor"]
    assert floor["ctc"]["2"]["mean"] == pytest.approx(0.02) and floor["ctc"]["2"]["std"] == 0.0
    missing = result["methods"]["u4d_no_temporal"]
    assert missing["ttce"] == {"missing": "poses.txt not found"} and missing["ctc"] == {
        "missing": "poses.txt not found"
    }
    assert missing["frd"] == {"missing": "no extractor given"} and "mean" not in json.dumps(missing)
    assert set(result["fusion"]) == {"gating", "add"}
    assert result["fusion"]["gating"]["ttce"]["3"]["mean"] == pytest.approx(0.4)
    assert result["fusion"]["add"]["ttce"]["3"] == {"mean": 0.6, "std": 0.0, "n": 1, "per_seed": [0.6]}
    assert result["intervals"] == {"ttce": [3, 4], "ttce_global": [3, 4], "ctc": [1, 2, 3, 4]}
    assert "ttce_global" not in most and "TTCE-global k=3" not in (tmp_path / "results" / "temporal.md").read_text()
    md = (tmp_path / "results" / "temporal.md").read_text()
    assert "## Table 2" in md and "## MoST fusion ablation" in md and "metres" in md and "m²" in md
    assert "| u4d_most | 2 | 0.3 ± 0.14 | 1.3 ± 0.14 |" in md
    assert "| u4d_no_temporal | 1 (< 2) | missing |" in md and "TTCE missing: poses.txt not found" in md
    assert "| add | 1 (< 2) | 0.6 ± 0 |" in md and "| floor | 2 (real data) | 0.1 ± 0 |" in md
    assert result["figure"] == "temporal.png" and "![TTCE and CTC against k](temporal.png)" in md
    assert "- fusion/add (1 seed): `" in md and "- methods/u4d_most (2 seeds): `" in md
    png = (tmp_path / "results" / "temporal.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_ttce_global_is_a_column_where_a_seed_computed_it(tmp_path):
    scored = evaluation(0.2, 0.1)
    scored["table2"]["bank"]["ttce_global"] = {"3": 0.05, "4": 0.07}
    with_global = write(tmp_path / "g", scored)
    without = write(tmp_path / "p", evaluation(0.4, 0.3))
    out = tmp_path / "t"
    assert table.main(["--method", f"a={with_global}", "--method", f"b={without}", "--out", str(out)]) == 0
    result = json.loads((tmp_path / "t.json").read_text())["methods"]
    assert result["a"]["ttce_global"]["4"] == {"mean": 0.07, "std": 0.0, "n": 1, "per_seed": [0.07]}
    assert "ttce_global" not in result["b"]
    md = (tmp_path / "t.md").read_text()
    assert "| TTCE-global k=3 (m) ↓ | TTCE-global k=4 (m) ↓ |" in md
    assert "| a | 1 (< 2) | 0.2 ± 0 | 1.2 ± 0 | 0.05 ± 0 | 0.07 ± 0 | 0.1 ± 0 |" in md
    assert "| b | 1 (< 2) | 0.4 ± 0 | 1.4 ± 0 | missing | missing | 0.3 ± 0 |" in md
    assert "- b: TTCE-global missing: not computed" in md


def test_one_seed_missing_of_two_keeps_the_other(tmp_path):
    good = write(tmp_path / "s0", evaluation(0.2, 0.1))
    bad = write(tmp_path / "s1", evaluation(0, 0, missing="frames are not consecutive"))
    out = tmp_path / "t"
    assert table.main(["--method", f"m={good}", "--method", f"m={bad}", "--out", str(out)]) == 0
    entry = json.loads((tmp_path / "t.json").read_text())["methods"]["m"]
    assert entry["ttce"]["3"] == {"mean": 0.2, "std": 0.0, "n": 1, "per_seed": [0.2, None]}
    assert entry["missing"] == {f"{bad}/evaluation.json": "frames are not consecutive"}
    assert "has no temporal metrics: frames are not consecutive" in (tmp_path / "t.md").read_text()


@pytest.mark.parametrize(
    ("content", "arg", "expected"),
    [
        (None, "m={dir}", "evaluation.json: not found"),
        ("{not json", "m={dir}", "not valid json"),
        ({"table1": {}}, "m={dir}", "no 'table2' object"),
        ({"table2": {"real": {}}}, "m={dir}", "table2.bank: expected an object"),
        ({"table2": {"bank": {"ttce": {"3": "x"}}}}, "m={dir}", "table2.bank.ttce.3: expected a number"),
        (evaluation(0.1, 0.1), "no-equals-sign", "expected NAME=DIR"),
        (evaluation(0.1, 0.1), "m=", "expected NAME=DIR"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, content, arg, expected):
    folder = tmp_path / "e"
    if content is None:
        folder.mkdir()
    else:
        write(folder, content)
    out = tmp_path / "o" / "temporal"
    assert table.main(["--method", arg.format(dir=folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_same_seed_twice_and_no_input_are_errors(tmp_path, capsys):
    folder = write(tmp_path / "e", evaluation(0.1, 0.1))
    assert table.main(["--method", f"m={folder}", "--method", f"m={folder}", "--out", str(tmp_path / "t")]) == 2
    assert table.main(["--out", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err
    assert "given twice" in err and "nothing to tabulate" in err
    assert not (tmp_path / "t.json").exists()


def test_intervals_are_the_metrics_own():
    from u4d_aug.metrics import temporal

    assert table.INTERVALS["ttce"] == tuple(str(k) for k in temporal.TTCE_INTERVALS)
    assert table.INTERVALS["ctc"] == tuple(str(k) for k in temporal.CTC_INTERVALS)


def test_the_nets_behind_each_seed_are_listed_for_two_nets_or_one(tmp_path, capsys):
    two = write(tmp_path / "two", evaluation(0.2, 0.1))
    (tmp_path / "two" / "budget.json").write_text(
        json.dumps({"nets": {"stage1": {"steps": 20, "minutes": 2.0}, "stage2": {"steps": 20, "minutes": 2.5}}})
    )
    one = write(tmp_path / "one", evaluation(0.3, 0.1))
    net = {"steps": 20, "minutes": 4.0, "stage": "u4d", "batch_size": 2}
    (tmp_path / "one" / "budget.json").write_text(json.dumps({"nets": {"u4d": net}}))
    bare = write(tmp_path / "bare", evaluation(0.3, 0.1))  # an evaluation without budget.json (e.g. the floor)
    args = ["--method", f"two={two}", "--method", f"one={one}", "--method", f"one={bare}", "--out", str(tmp_path / "t")]
    assert table.main(args) == 0
    methods = json.loads((tmp_path / "t.json").read_text())["methods"]
    assert list(methods["two"]["nets"][0]) == ["stage1", "stage2"] and methods["one"]["nets"] == [{"u4d": net}, None]
    md = (tmp_path / "t.md").read_text()
    assert "trained: stage1 20 steps (2.0 min) + stage2 20 steps (2.5 min)" in md
    assert "trained: u4d 20 steps x batch 2 (4.0 min); —" in md
    (tmp_path / "bare" / "budget.json").write_text(json.dumps({"nets": {"u4d": {"minutes": 1}}}))
    assert table.main(args) == 2 and "budget.json: expected" in capsys.readouterr().err
