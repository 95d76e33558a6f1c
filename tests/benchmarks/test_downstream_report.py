"""benchmarks/downstream_report.py: summary.json in percent with seed-paired differences (95 % CI, paired t-test p,
seeds needed), report.md and figures from `u4d experiment` results.json files; bad settings and files in one line."""

from __future__ import annotations

import json
import math

import pytest
from scipy import stats

from segmentation.experiment import aggregate
from tests.tiny_nets import REPO, load_script

report = load_script("downstream_report")
REAL = REPO / "benchmarks" / "results" / "segmentation" / "experiment_cpu_tenpct_seq" / "b1500_results.json"
T_975_DF2 = 4.302652729911275  # Student t, 97.5 % quantile, 2 degrees of freedom (tables)


def fake_run(seed: int, miou: float, ece: float, car: float, bands: bool = False) -> dict:
    """One finished run as results.json lists it (fractions; wall-clock 60 s x (seed + 1))."""
    run = {"seed": seed, "miou": miou, "ece_per_scan": ece, "ece_pooled": ece / 2, "iou": {"car": car, "road": 0.9}}
    run.update(wall_clock_s=60.0 * (seed + 1), out_dir=f"runs/x/seed{seed}")
    if bands:  # a full evaluation's distance bands
        run["bands"] = [{"range": [0, 10], "miou": miou + 0.05}, {"range": [10, None], "miou": miou - 0.05}]
    return run


def fake_arm(name: str, runs: list[dict], backbone: str = "minkunet", status: str | None = None, **extra) -> dict:
    """An arm entry as experiment.run_experiment_config writes it: aggregate() of its runs, or status and reason."""
    entry = {"arm": name, "mode": "supervised" if name == "sup-only" else "semi", "backbone": backbone, "bank": None}
    if not runs:
        return {**entry, "status": status or "not run", "reason": "no finished run", **extra}
    return {**entry, "status": status or "done", **aggregate(runs), "runs": runs, **extra}


def ten_percent() -> dict:
    """sup-only, mt, mt+u4d on seeds 0-2 (hand-picked numbers), mt+r2dm missing, mt+u4d-random on seed 0 only."""
    arms = [
        fake_arm(
            "sup-only", [fake_run(s, m, e, 0.3) for s, m, e in zip(range(3), (0.40, 0.42, 0.44), (0.06, 0.07, 0.08))]
        ),
        fake_arm(
            "mt",
            [fake_run(s, m, e, 0.5, True) for s, m, e in zip(range(3), (0.45, 0.46, 0.47), (0.05, 0.05, 0.06))],
            reliability_png="reliability_mt_minkunet.png",
        ),
        {
            **fake_arm("mt+r2dm", []),
            "status": "missing",
            "reason": "bank banks/r2dm_hdl64 not found (generate it first)",
        },
        fake_arm(
            "mt+u4d",
            [
                fake_run(s, m, e, c, True)
                for s, m, e, c in zip(range(3), (0.46, 0.48, 0.50), (0.04, 0.05, 0.05), (0.52, 0.54, 0.56))
            ],
            reliability_png="reliability_mt+u4d_minkunet.png",  # named but absent
        ),
        fake_arm("mt+u4d-random", [fake_run(0, 0.47, 0.05, 0.5)], status="partial"),
    ]
    return {"config": {"seeds": [0, 1, 2], "final_eval": True}, "arms": arms, "contrasts": []}


def one_percent() -> dict:
    """Two backbones in one file: minkunet and spvcnn, sup-only and mt on seeds 0-1, no distance bands."""
    arms = []
    for backbone, shift in (("minkunet", 0.0), ("spvcnn", 0.1)):
        arms.append(fake_arm("sup-only", [fake_run(s, 0.20 + shift, 0.1, 0.1) for s in range(2)], backbone))
        arms.append(fake_arm("mt", [fake_run(s, 0.22 + shift + 0.01 * s, 0.1, 0.1) for s in range(2)], backbone))
    return {"config": {"seeds": [0, 1]}, "arms": arms, "learning_curves_png_spvcnn": "learning_curves_spvcnn.png"}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The script run on the two synthetic settings: (out folder, summary, report text)."""
    root = tmp_path_factory.mktemp("downstream")
    (root / "ten").mkdir()
    (root / "ten" / "results.json").write_text(json.dumps(ten_percent()))
    (root / "ten" / "reliability_mt_minkunet.png").write_bytes(b"a reliability png")
    (root / "one").mkdir()
    (root / "one" / "results.json").write_text(json.dumps(one_percent()))
    (root / "one" / "learning_curves_spvcnn.png").write_bytes(b"a learning curve png")
    out = root / "out"
    argv = ["--setting", f"10pct/minkunet={root / 'ten' / 'results.json'}"]
    argv += ["--setting", f"1pct/spvcnn={root / 'one' / 'results.json'}", "--out", str(out)]
    assert report.main(argv) == 0
    return out, json.loads((out / "summary.json").read_text()), (out / "report.md").read_text()


def test_arms_in_percent_with_per_seed_values(written):
    _, summary, _ = written
    assert list(summary) == ["10pct/minkunet", "1pct/spvcnn"]
    ten = summary["10pct/minkunet"]
    assert (ten["backbone"], ten["seeds"], ten["config_seeds"], ten["final_eval"]) == (
        "minkunet",
        [0, 1, 2],
        [0, 1, 2],
        True,
    )
    mt = ten["arms"]["mt"]
    assert mt["status"] == "done" and mt["seeds"] == [0, 1, 2]
    assert mt["miou"]["per_seed"] == pytest.approx([45.0, 46.0, 47.0])
    assert (mt["miou"]["mean"], mt["miou"]["std"], mt["miou"]["n"]) == (pytest.approx(46.0), pytest.approx(1.0), 3)
    assert mt["ece"]["mean"] == pytest.approx(16 / 3) and mt["ece"]["per_seed"] == pytest.approx([5.0, 5.0, 6.0])
    assert mt["ece_pooled"]["mean"] == pytest.approx(8 / 3)
    assert mt["wall_clock_s"]["per_seed"] == [60.0, 120.0, 180.0]  # seconds, not scaled
    assert mt["iou"]["car"]["mean"] == pytest.approx(50.0) and mt["bands"]["0-10 m"]["mean"] == pytest.approx(51.0)
    assert ten["arms"]["mt+u4d-random"]["status"] == "partial" and ten["arms"]["mt+u4d-random"]["seeds"] == [0]
    # the backbone after '/' picks the file's spvcnn entries (mIoU 0.32 and 0.33 for mt)
    assert summary["1pct/spvcnn"]["arms"]["mt"]["miou"]["per_seed"] == pytest.approx([32.0, 33.0])


def test_arm_without_finished_run_has_status_and_no_numbers(written):
    _, summary, text = written
    ten = summary["10pct/minkunet"]
    reason = "bank banks/r2dm_hdl64 not found (generate it first)"
    assert ten["arms"]["mt+r2dm"] == {"status": "missing", "mode": "semi", "bank": None, "reason": reason}
    assert not [key for key in ten["paired"] if "mt+r2dm" in key]
    assert ten["unpaired"]["mt+r2dm_vs_mt"] == "mt+r2dm missing"
    assert ten["unpaired"]["mt+u4d_vs_mt+r2dm"] == "mt+r2dm missing"
    assert f"| mt+r2dm | missing: {reason} | - | - |" in text


def test_paired_difference_mean_ci_p_and_seeds_needed_by_hand(written):
    _, summary, _ = written
    paired = summary["10pct/minkunet"]["paired"]
    assert list(paired) == ["mt_vs_sup-only", "mt+u4d_vs_mt+u4d-random", "mt+u4d_vs_mt", "mt+u4d-random_vs_mt"]
    miou = paired["mt+u4d_vs_mt"]["miou"]  # per seed +1, +2, +3 points
    top = paired["mt+u4d_vs_mt"]
    assert (top["mean"], top["ci95"], top["p"]) == (miou["mean"], miou["ci95"], miou["p"])  # the headline keys
    assert miou["seeds"] == [0, 1, 2] and miou["per_seed"] == pytest.approx([1.0, 2.0, 3.0]) and miou["n"] == 3
    assert (miou["mean"], miou["std"]) == (pytest.approx(2.0), pytest.approx(1.0))
    half = T_975_DF2 * 1.0 / math.sqrt(3)
    assert miou["ci95"] == pytest.approx([2.0 - half, 2.0 + half])
    # paired t = 2 / (1 / sqrt 3) = sqrt 12; with 2 degrees of freedom p = 1 - t / sqrt(2 + t^2) = 1 - sqrt(6 / 7)
    assert miou["p"] == pytest.approx(1 - math.sqrt(6 / 7))
    assert miou["p"] == pytest.approx(stats.ttest_rel([46, 48, 50], [45, 46, 47]).pvalue)
    assert miou["seeds_needed"] == 4  # t(n-1)/sqrt(n) < 2 first at n = 4: 12.71/1.41, 4.30/1.73, 3.18/2 = 1.59
    assert paired["mt+u4d_vs_mt"]["ece"]["per_seed"] == pytest.approx([-1.0, 0.0, -1.0])
    assert paired["mt+u4d_vs_mt"]["iou"]["car"]["mean"] == pytest.approx(4.0)
    assert paired["mt+u4d_vs_mt"]["iou"]["road"]["p"] is None  # the same IoU on every seed
    assert paired["mt+u4d_vs_mt"]["bands"][">= 10 m"]["mean"] == pytest.approx(2.0)
    assert paired["mt_vs_sup-only"]["miou"]["p"] == pytest.approx(1 - math.sqrt(0.96))  # t = sqrt 48
    one_seed = paired["mt+u4d_vs_mt+u4d-random"]["miou"]
    assert one_seed["per_seed"] == pytest.approx([-1.0]) and one_seed["n"] == 1
    assert one_seed["ci95"] is None and one_seed["p"] is None and one_seed["seeds_needed"] is None


def test_report_says_which_differences_are_inside_the_noise(written):
    _, _, text = written
    assert "**mt+u4d − mt**: mIoU +2.00 ± 1.00 points over 3 seeds, 95 % CI [-0.48, +4.48], p = 0.074: the CI " in text
    assert "contains 0, inside the seed noise (about 4 paired seeds would resolve" in text
    assert "**mt − sup-only**: mIoU +4.00 ± 1.00 points over 3 seeds, 95 % CI [+1.52, +6.48], p = 0.02: the CI " in text
    assert "excludes 0, outside the seed noise (mt higher)" in text
    assert "mIoU -1.00 points on the one seed both finished (0): no confidence interval" in text
    # an arm on one seed has no spread: its mean alone, marked, not "± 0.00"
    one = (
        "| mt+u4d-random | partial | 0 | 47.00 (1 seed) | 47.00 | 5.00 (1 seed) | 5.00 | 2.50 (1 seed) | 1.0 (1 seed) |"
    )
    assert one in text
    assert "| -1.00 (1 seed) |" in text
    # per class, one column (mt+u4d - mt+r2dm has no numbers): car +2, +4, +6 points, CI [-0.97, +8.97] holds 0
    assert "| class | mt+u4d − mt (3 seeds) |\n|---|---|\n| car | +4.00 |\n| road | +0.00 |" in text
    assert "| 0-10 m |" in text  # 10 %: bands carried
    assert "Absent: the runs carry no distance-band metrics" in text  # 1 %: none


def test_figures_drawn_and_copied(written):
    out, summary, text = written
    figures = summary["10pct/minkunet"]["figures"]
    assert figures["paired"] == "10pct_minkunet_paired.png" and figures["per_class"] == "10pct_minkunet_per_class.png"
    for name in (figures["paired"], figures["per_class"]):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert figures["reliability"] == {"mt": "10pct_minkunet_reliability_mt.png"}
    assert (out / "10pct_minkunet_reliability_mt.png").read_bytes() == b"a reliability png"
    assert figures["not_found"] == ["reliability_mt+u4d_minkunet.png"]
    assert summary["1pct/spvcnn"]["figures"]["learning_curves"] == "1pct_spvcnn_learning_curves.png"
    assert (out / "1pct_spvcnn_learning_curves.png").read_bytes() == b"a learning curve png"
    assert "[10pct_minkunet_paired.png](10pct_minkunet_paired.png)" in text
    assert not list(out.glob(".*.tmp"))  # atomic writes left no temp file


def test_real_experiment_file_with_renamed_arms(tmp_path):
    out = tmp_path / "out"
    argv = ["--setting", f"10pct/minkunet={REAL}", "--rename", "sup-only-1500=sup-only"]
    assert report.main([*argv, "--rename", "mt-a12-w05-1500=mt", "--out", str(out)]) == 0
    setting = json.loads((out / "summary.json").read_text())["10pct/minkunet"]
    paired = setting["paired"]["mt_vs_sup-only"]
    assert round(paired["miou"]["mean"], 2) == 1.98 and paired["miou"]["n"] == 4
    assert paired["miou"]["p"] == pytest.approx(0.136, abs=1e-3)
    stored = json.loads(REAL.read_text())["contrasts"][0]  # the experiment's own contrast, in fractions
    assert paired["miou"]["mean"] == pytest.approx(100 * stored["miou"]["mean"])
    assert paired["ece"]["p"] == pytest.approx(stored["ece_per_scan"]["p"])
    assert setting["arms"]["sup-only"]["status"] == "done"  # the unfinished arm called sup-only gave way
    assert setting["renamed"] == {"sup-only-1500": "sup-only", "mt-a12-w05-1500": "mt"}
    assert (out / "10pct_minkunet_reliability_mt.png").is_file() and (out / "report.md").is_file()


@pytest.mark.parametrize(
    ("make_args", "message"),
    [
        (lambda d: ["--setting", "10pct/minkunet"], "--setting '10pct/minkunet': expected NAME=PATH"),
        (lambda d: ["--setting", f"a/minkunet={d / 'nope.json'}"], "nope.json: not found"),
        (lambda d: ["--setting", f"a/minkunet={d / 'bad.json'}"], "bad.json: not valid json"),
        (
            lambda d: ["--setting", f"a/minkunet={d / 'arms.json'}"],
            "arms.json: expected a `u4d experiment` results.json",
        ),
        (lambda d: ["--setting", f"a/spvcnn={d / 'good.json'}"], "good.json: no arm with backbone 'spvcnn'"),
        (lambda d: ["--setting", f"a/minkunet={d / 'escape.json'}"], "escape.json: arms[0]: the arm name '../x'"),
        (lambda d: ["--setting", f"a/minkunet={d / 'good.json'}", "--rename", "mt"], "--rename 'mt': expected OLD=NEW"),
        (lambda d: ["--setting", f"a/minkunet={d / 'good.json'}", "--rename", "x=y"], "no setting has an arm 'x'"),
    ],
)
def test_bad_input_is_one_line_naming_the_field(tmp_path, capsys, make_args, message):
    (tmp_path / "bad.json").write_text('{"arms": [')
    (tmp_path / "arms.json").write_text('{"runs": []}')
    (tmp_path / "good.json").write_text(json.dumps(ten_percent()))
    escape = ten_percent()
    escape["arms"][0]["arm"] = "../x"  # an arm name would name a copied figure outside --out
    (tmp_path / "escape.json").write_text(json.dumps(escape))
    assert report.main([*make_args(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()  # nothing written before every input is read


def test_pairs_skip_reverses_and_percent_scales_fractions():
    names = ["sup-only", "mt", "mt+r2dm", "mt+u4d"]
    assert report.pair_names(names) == [
        ("mt", "sup-only"),
        ("mt+u4d", "mt+u4d-random"),
        ("mt+r2dm", "mt"),
        ("mt+u4d", "mt"),
        ("mt+u4d", "mt+r2dm"),  # sup-only is paired with mt only
    ]
    stat = {"mean": 0.02, "std": 0.01, "n": 2, "per_seed": [0.01, None], "ci95": [-0.1, 0.14], "p": 0.3}
    scaled = report.percent(stat)
    assert (scaled["mean"], scaled["std"], scaled["n"], scaled["p"]) == (2.0, 1.0, 2, 0.3)  # p and n unscaled
    assert scaled["per_seed"] == [1.0, None] and scaled["ci95"] == pytest.approx([-10.0, 14.0])
    assert stat["mean"] == 0.02  # the input is left as it was


def test_bank_fidelity_joins_the_arm_that_reads_the_bank(tmp_path):
    """--bank-eval: the evaluation.json values of a bank reach the arm whose `bank` it is, merged over folders."""
    results = ten_percent()
    results["arms"][3]["bank"] = "banks/u4d_hdl64"  # mt+u4d
    (tmp_path / "results.json").write_text(json.dumps(results))
    geometry = {
        "table1": {"jsd": {"value": 0.25}, "mmd": {"value": 43.6}, "points": {"value": 55758.0, "real": 121486.0}}
    }
    intensity = {"table1": {"intensityjs": {"value": 0.338, "mean": 0.287, "real_mean": 0.298}, "frd": {"value": None}}}
    for name, table in (("geo", geometry), ("int", intensity)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "evaluation.json").write_text(
            json.dumps({**table, "real": "data/sim", "real_sequences": ["88"]})
        )
    argv = ["--setting", f"10pct/minkunet={tmp_path / 'results.json'}", "--out", str(tmp_path / "out")]
    argv += [
        "--bank-eval",
        f"banks/u4d_hdl64={tmp_path / 'geo'}",
        "--bank-eval",
        f"banks/u4d_hdl64/={tmp_path / 'int'}",
    ]
    assert report.main(argv) == 0
    arms = json.loads((tmp_path / "out" / "summary.json").read_text())["10pct/minkunet"]["arms"]
    fidelity = arms["mt+u4d"]["bank_fidelity"]
    assert (fidelity["jsd"], fidelity["mmd"], fidelity["intensityjs"]) == (0.25, 43.6, 0.338)
    assert (fidelity["points"], fidelity["real_points"]) == (55758.0, 121486.0)
    assert (fidelity["intensity_mean"], fidelity["real_intensity_mean"]) == (0.287, 0.298)
    assert "frd" not in fidelity and len(fidelity["sources"]) == 2  # a null value is no number
    assert all("bank_fidelity" not in arm for name, arm in arms.items() if name != "mt+u4d")
    text = (tmp_path / "out" / "report.md").read_text()
    assert "| mt+u4d | banks/u4d_hdl64 | 0.250 | 43.6 | 0.338 | 55,758 (121,486) | 0.287 (0.298) |" in text
    argv[-1] = f"banks/other={tmp_path / 'int'}"
    assert report.main(argv) == 2  # a bank no arm reads is a mistake, not a silent no-op


def test_provenance_from_records_and_pairs_on_different_burn_ins(tmp_path):
    """Runs with records name their host, steps and minutes, burn-in and bank scans; a pair whose burn-ins differ is
    listed."""

    def with_record(run: dict, cpu: str, burn_in: str, bank: str | None = None) -> dict:
        banks = [{"content_sha256": bank}] if bank else []
        record = {"host": {"cpu": cpu, "torch": "2.13.0+cpu"}, "burn_in_weights": burn_in, "banks": banks}
        return {**run, **record, "step": 1500}

    mt = [with_record(fake_run(s, 0.45 + s / 100, 0.05, 0.5), "Intel Xeon", f"b{s}") for s in range(2)]
    bank = [with_record(fake_run(0, 0.47, 0.05, 0.5), "Intel Xeon", "b0", "c0ffee")]
    bank.append(with_record(fake_run(1, 0.48, 0.05, 0.5), "AMD EPYC", "other", "beef"))
    arms = [fake_arm("mt", mt), {**fake_arm("mt+u4d", bank), "bank": "banks/u4d"}]
    (tmp_path / "results.json").write_text(json.dumps({"config": {"seeds": [0, 1]}, "arms": arms}))
    out = tmp_path / "out"
    assert report.main(["--setting", f"10pct/minkunet={tmp_path / 'results.json'}", "--out", str(out)]) == 0
    setting = json.loads((out / "summary.json").read_text())["10pct/minkunet"]
    assert setting["arms"]["mt+u4d"]["provenance"][1] == {
        "seed": 1, "cpu": "AMD EPYC", "torch": "2.13.0+cpu", "steps": 1500, "minutes": 2.0, "burn_in_weights": "other",
        "bank_content": ["beef"],
    }  # fmt: skip
    assert setting["paired"]["mt+u4d_vs_mt"]["burn_in_differs"] == [1]
    text = (out / "report.md").read_text()
    assert "| 1 | mt+u4d | AMD EPYC | 2.13.0+cpu | 1,500 | 2.0 | other | beef |" in text
    assert "| 0 | mt | Intel Xeon | 2.13.0+cpu | 1,500 | 1.0 | b0 | - |" in text
    assert "started from different burn-in weights" in text and "mt+u4d − mt (seeds 1)" in text


def test_ceiling_share_by_hand_and_its_bootstrap():
    """(bank − mt) / (real − mt) over the common seeds: gains 1, 2, 3 against ceiling gains 2, 4, 6 -> 50 %; every
    bootstrap draw keeps the pairs, so each has ratio 0.5 as well; a ceiling that lost in some seed leaves draws out."""
    mt = {"status": "done", "seeds": [0, 1, 2, 3], "miou": {"per_seed": [40.0, 41.0, 42.0, 43.0]}}
    real = {"status": "done", "seeds": [0, 1, 2], "miou": {"per_seed": [42.0, 45.0, 48.0]}}
    bank = {"status": "done", "bank": "banks/u4d", "seeds": [0, 1, 2], "miou": {"per_seed": [41.0, 43.0, 45.0]}}
    share = report.ceiling_share(bank, real, mt, draws=500)
    assert share["seeds"] == [0, 1, 2] and share["share"] == pytest.approx(0.5)
    assert share["gain"] == pytest.approx(2.0) and share["ceiling_gain"] == pytest.approx(4.0)
    assert share["ci95"] == pytest.approx([0.5, 0.5]) and share["unresolved"] == 0.0
    losing = {**real, "miou": {"per_seed": [39.0, 45.0, 48.0]}}  # ceiling gain -1 at seed 0
    share = report.ceiling_share(bank, losing, mt, draws=2000)
    assert 0 < share["unresolved"] < 0.1  # draws of seed 0 alone (1/27) have no ratio
    assert share["share"] == pytest.approx(2 / 3) and share["ci95"][0] < 2 / 3 < share["ci95"][1]
    # fewer than 2 common seeds: no share; ceiling_shares skips the ceiling itself and arms without a bank
    assert report.ceiling_share(bank, {**real, "seeds": [0], "miou": {"per_seed": [42.0]}}, mt) is None
    arms = {"mt": mt, "mt+real": {**real, "bank": "banks/real"}, "mt+real-raw": {**real, "bank": "r"}, "mt+u4d": bank}
    assert list(report.ceiling_shares(arms)) == ["mt+u4d"]
    assert report.ceiling_shares({"mt": mt, "mt+u4d": bank}) == {}
    lines = report.ceiling_table(report.ceiling_shares(arms), arms)
    assert any(line.startswith("| mt+u4d | 3 | +2.00 | +4.00 | 50 % | [50 %, 50 %] | 0 % |") for line in lines)
