"""benchmarks/reports/learning_curve.py on hand-made milestone folders: each method's rows in step order (10 after 2,
not before), the real rows as the reference, the PNG written; a missing row or no milestone is one line."""

from __future__ import annotations

import json

from tests.tiny_nets import load_script

curve = load_script("reports/learning_curve")
REAL = {"real": {"fpd": 106.0, "teacher_building_share": 0.227}, "real projected": {"fpd": 103.0}}


def _milestone(folder, method, step, fpd, building, prefix=""):
    folder.mkdir(parents=True, exist_ok=True)
    rows = {**REAL, "reference": {}, f"{prefix}{method}_{step}": {"fpd": fpd, "teacher_building_share": building}}
    (folder / f"{prefix}gates_{step}.json").write_text(json.dumps({"rows": rows}))


def test_curves_by_step_beside_the_real_rows(tmp_path):
    final = tmp_path / "final"
    for step, fpd, building in ((10, 900.0, 0.05), (2, 5000.0, 0.01)):
        _milestone(final / "u4d_milestones", "u4d", step, fpd, building)
    _milestone(final / "baseline_milestones", "baseline", 2, 4000.0, 0.02)
    out = tmp_path / "out" / "curve.json"
    assert curve.main(["--final", str(final), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert list(result["methods"]["u4d"]) == ["2", "10"]
    assert result["methods"]["u4d"]["10"]["fpd"] == 900.0 and result["methods"]["baseline"]["2"]["frd"] is None
    assert result["reference"]["real"]["teacher_building_share"] == 0.227
    rows = [line for line in out.with_suffix(".md").read_text().splitlines() if line.startswith("| ")][1:]
    assert rows[0].startswith("| real | — | 106 |") and rows[2].startswith("| u4d | 2 | 5,000 | — | 1.0 |")
    assert rows[3].startswith("| u4d | 10 | 900 |") and rows[4].startswith("| baseline | 2 | 4,000 |")
    assert out.with_suffix(".png").stat().st_size > 10_000


def test_a_milestone_without_its_row_and_an_empty_folder_are_one_line(tmp_path, capsys):
    final = tmp_path / "final"
    (final / "u4d_milestones").mkdir(parents=True)
    assert curve.main(["--final", str(final), "--out", str(tmp_path / "c.json")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {final}: no METHOD_milestones/gates_STEP.json for u4d baseline"
    (final / "u4d_milestones" / "gates_4.json").write_text(json.dumps({"rows": {"u4d_8": {}}}))
    assert curve.main(["--final", str(final), "--out", str(tmp_path / "c.json")]) == 2
    assert "gates_4.json: no row 'u4d_4'" in capsys.readouterr().err


def test_a_prefix_reads_the_cascade_banks_and_the_plain_curve_skips_them(tmp_path):
    final = tmp_path / "final"
    _milestone(final / "u4d_milestones", "u4d", 2, 400.0, 0.01)
    _milestone(final / "u4d_milestones", "u4d", 2, 300.0, 0.02, prefix="cascade_")
    _milestone(final / "u4d_milestones", "u4d", 4, 200.0, 0.03, prefix="cascade_")
    out = tmp_path / "c.json"
    assert curve.main(["--final", str(final), "--methods", "u4d", "--prefix", "cascade_", "--out", str(out)]) == 0
    assert {step: row["fpd"] for step, row in json.loads(out.read_text())["methods"]["u4d"].items()} == {
        "2": 300.0, "4": 200.0,
    }  # fmt: skip
    assert curve.main(["--final", str(final), "--methods", "u4d", "--out", str(out)]) == 0
    assert {step: row["fpd"] for step, row in json.loads(out.read_text())["methods"]["u4d"].items()} == {"2": 400.0}
