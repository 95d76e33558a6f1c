"""benchmarks/reports/pilot_table.py on hand-made pilot folders: budgets from the run logs, the probe's errors at the
three log-SNRs, gate rows from a pilot's own gates.json or a shared file, the reference rows first; bad input is one
line."""

from __future__ import annotations

import json

from tests.tiny_nets import load_script

pilot_table = load_script("reports/pilot_table")


def _run(folder, steps, batch, seconds):
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(f"stage: u4d\nbatch_size: {batch}\n")
    lines = [{"step": 50 * (i + 1), "sec_per_step": s} for i, s in enumerate(seconds)]
    lines[-1]["step"] = steps
    (folder / "log.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))


def _probe(folder, nets):
    rows = {
        task: {"rows": [{"log_snr": lam, "error": err} for lam, err in errs.items()]} for task, errs in nets.items()
    }
    (folder / "denoise.json").write_text(json.dumps({"nets": rows}))


def test_the_table_reads_budgets_probes_and_gates(tmp_path):
    pilots = tmp_path / "pilots"
    _run(pilots / "shared" / "net", 1500, 4, [0.9, 0.7, 0.8])
    _probe(
        pilots / "shared",
        {"stage1": {2.0: 0.1, 5.0: 0.07, 8.0: 0.02}, "stage2": {2.0: 0.066, 5.0: 0.033, 8.0: 0.013, 11.0: 0.9}},
    )
    (pilots / "shared" / "gates.json").write_text(
        json.dumps({"rows": {"shared": {"teacher_building_share": 0.011, "fpd": 30233.0}}})
    )
    _run(pilots / "two_nets" / "stage1", 750, 4, [0.5])
    _run(pilots / "two_nets" / "stage2", 750, 4, [0.6, 0.6])
    _probe(pilots / "two_nets", {"stage2": {2.0: 0.0827, 5.0: 0.0445, 8.0: 0.014}})
    (pilots / "notes").mkdir()  # no denoise.json: not a pilot
    shared_gates = tmp_path / "gates_round1.json"
    reference = {"teacher_kept_share": 0.713, "bev_points_per_cell": 10.91}
    two_nets = {"teacher_building_share": 0.194, "frd": 11807.0}
    shared_gates.write_text(json.dumps({"rows": {"reference": reference, "two_nets": two_nets}}))
    out = tmp_path / "pilots.json"
    assert pilot_table.main(["--pilots", str(pilots), "--gates", str(shared_gates), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert list(result["pilots"]) == ["shared", "two_nets"] and list(result["reference"]) == ["reference"]
    shared = result["pilots"]["shared"]
    assert shared["runs"] == {"net": {"steps": 1500, "batch": 4, "sec_per_step": 0.8}}
    assert shared["denoise_error"]["stage2"] == {"2": 0.066, "5": 0.033, "8": 0.013}  # log-SNR 11 is not a probe column
    assert shared["gates"]["fpd"] == 30233.0 and shared["gates"]["frd"] is None
    assert result["pilots"]["two_nets"]["gates"]["teacher_building_share"] == 0.194
    table = out.with_suffix(".md").read_text().splitlines()
    body = [line for line in table if line.startswith("| ")][1:]
    assert body[0].startswith("| reference | — |") and "71.3" in body[0] and "10.91" in body[0]
    assert (
        body[1].startswith("| shared | 1500 x 4 | 0.80 | 0.0660 / 0.0330 / 0.0130 | 0.0700 |") and "30,233" in body[1]
    )
    assert body[2].startswith("| two_nets | 750 x 4 + 750 x 4 | 0.50 / 0.60 | 0.0827 / 0.0445 / 0.0140 | nan |")
    assert "19.4" in body[2] and "11,807" in body[2]


def test_a_folder_without_pilots_is_one_line(tmp_path, capsys):
    (tmp_path / "pilots").mkdir()
    assert pilot_table.main(["--pilots", str(tmp_path / "pilots"), "--out", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {tmp_path / 'pilots'}: no pilot folder with a denoise.json"]
