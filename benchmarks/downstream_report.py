"""The downstream answer: `u4d experiment` results of up to three settings (label share / backbone) side by side.

    python benchmarks/downstream_report.py --setting 10pct/minkunet=runs/downstream_10pct/results.json \
        --setting 1pct/minkunet=runs/downstream_1pct/results.json --out benchmarks/results/downstream

Reads each setting's results.json (segmentation/experiment.py; the part of the setting's name after '/' picks the
backbone) and writes to --out: summary.json, report.md and per setting (SETTING = its name with '/' as '_')
SETTING_paired.png (seed-paired differences with 95 % confidence intervals), SETTING_per_class.png (per-class IoU of
mt+u4d against mt and mt+r2dm) and copies of the reliability diagrams and learning curves that results.json names
(SETTING_reliability_ARM.png, SETTING_learning_curves.png). Nothing is recomputed from predictions: the arm figures
are results.json's (`experiment.aggregate`), the paired ones `experiment.paired_arms` on its runs.
`--rename OLD=NEW` renames an arm in every file (to report an experiment whose arms carry other names); an unfinished
arm already called NEW gives way to it. `--bank-eval BANK=DIR` (repeatable; the same BANK may name several folders)
adds what `u4d evaluate --json --out DIR` measured of the bank an arm reads (BANK as the arm's `bank` in results.json,
e.g. banks/u4d_hdl64) to that arm: how close its scans are to the real ones, beside what they did downstream.

summary.json is {SETTING: ...}; metrics are in percent (fractions x 100), wall-clock in seconds; every `per_seed` is
a list aligned with the `seeds` list beside it (null where a run lacks the metric):
    source, backbone, final_eval, seeds (finished in some arm), config_seeds, renamed {OLD: NEW}, units
    arms.ARM: status, mode, bank; unfinished arms add reason and no number; finished (done | partial) arms add
        seeds, miou / ece (per scan, Calib3D) / ece_pooled / wall_clock_s: {mean, std, n, per_seed},
        iou.CLASS and bands.BAND: {mean, std, n}; bank_fidelity (with --bank-eval): {METRIC: value (jsd, mmd x1e4,
        rangejs, intensityjs, points, frd, fpd as `u4d evaluate` reports them), real_points, intensity_mean,
        real_intensity_mean, real (the reference root and sequences), sources}
        provenance: [{seed, cpu, torch, steps, minutes, burn_in_weights, bank_content}] (null where no record)
    paired.A_vs_B (A - B on the seeds both finished): arm, reference, miou / ece: {seeds, per_seed, mean, std, n,
        above, ci95 [lo, hi] (t distribution), p (two-sided paired t-test), seeds_needed}, iou.CLASS / bands.BAND alike;
        mean, ci95, p at the top are the mIoU difference's (the headline: `paired.A_vs_B.mean` / `.ci95` / `.p`)
    unpaired.A_vs_B: why the pair has no numbers
    ceiling_share.ARM (bank arms, when mt+real and mt finished): (ARM − mt) / (mt+real − mt) of the mIoU means over
        the seeds all three finished: seeds, share (null when the ceiling gain is <= 0), gain, ceiling_gain (points),
        ci95 (percentile bootstrap over seeds), unresolved (share of draws with ceiling gain <= 0), draws
    figures: paired, per_class, learning_curves, reliability.ARM (file names in --out; null = not drawn), not_found
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from segmentation.experiment import MAX_SEEDS_ESTIMATE, mean_std, mean_text, paired_arms
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import (
    atomic_open,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    make_folder,
    read_json_file,
)
from u4d_aug.validate import check_plain_name

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "downstream"
FINISHED = ("done", "partial")
REFERENCES = ("mt", "mt+r2dm")  # every mean-teacher arm is paired with each of these (sup-only only via NAMED_PAIRS)
NAMED_PAIRS = (("mt", "sup-only"), ("mt+u4d", "mt+u4d-random"))
PRESENT_PAIRS = (
    ("mt+real-raw", "mt+real"),
)  # paired when both arms are in the setting (the projection's cost)  # (arm, reference): arm - reference
CLASS_PAIRS = (("mt+u4d", "mt"), ("mt+u4d", "mt+r2dm"))  # the per-class table and chart
ARM_METRICS = (("miou", "miou"), ("ece", "ece_per_scan"), ("ece_pooled", "ece_pooled"))  # summary key, results key
EXAMPLE = "10pct/minkunet=runs/downstream_10pct/results.json"


# ------------------------------------------------------------------------------------------------- inputs


def parse_setting(text: str) -> tuple[str, str | None, Path]:
    """'NAME=PATH' -> (NAME, the backbone after NAME's last '/' or None, PATH)."""
    name, sep, path = text.partition("=")
    if not sep or not name.strip() or not path.strip():
        raise InputError(f"--setting {text!r}: expected NAME=PATH, e.g. {EXAMPLE}")
    check_plain_name(name.replace("/", "_"), f"--setting {text!r}: the name")
    backbone = name.rsplit("/", 1)[1] if "/" in name else None
    if backbone == "":
        raise InputError(f"--setting {text!r}: nothing after '/' to name the backbone, e.g. {EXAMPLE}")
    return name, backbone, Path(path)


def parse_renames(texts: list[str]) -> dict[str, str]:
    """['OLD=NEW', ...] -> {OLD: NEW}."""
    renames: dict[str, str] = {}
    for text in texts:
        old, sep, new = text.partition("=")
        if not sep or not old or not new or old in renames:
            raise InputError(f"--rename {text!r}: expected OLD=NEW, once per OLD, e.g. sup-only-1500=sup-only")
        renames[old] = check_plain_name(new, f"--rename {text!r}: the new name")
    return renames


def read_bank_evals(texts: list[str]) -> dict[str, dict]:
    """['BANK=DIR', ...] -> {BANK: bank_fidelity}: the table-1 values of each DIR/evaluation.json, merged per BANK."""
    fidelity: dict[str, dict] = {}
    for text in texts:
        bank, sep, folder = text.partition("=")
        if not sep or not bank.strip() or not folder.strip():
            raise InputError(f"--bank-eval {text!r}: expected BANK=DIR, e.g. banks/u4d_hdl64=runs/eval_u4d")
        path = Path(folder) / "evaluation.json" if Path(folder).suffix != ".json" else Path(folder)
        result = read_json_file(path, "the evaluation.json that `u4d evaluate --json --out DIR` writes")
        table = result.get("table1") if isinstance(result, dict) else None
        if not isinstance(table, dict) or not table:
            raise InputError(f"{path}: no 'table1' object (expected the evaluation.json of `u4d evaluate`)")
        entry = fidelity.setdefault(bank.strip().rstrip("/"), {"sources": []})
        entry["sources"].append(str(path))
        entry["real"] = {"root": result.get("real"), "sequences": result.get("real_sequences")}
        for metric, value in table.items():
            if isinstance(value, dict) and isinstance(value.get("value"), (int, float)):
                entry[metric] = float(value["value"])
        points, intensity = table.get("points") or {}, table.get("intensityjs") or {}
        for key, source, field in (("real_points", points, "real"), ("intensity_mean", intensity, "mean"),
                                   ("real_intensity_mean", intensity, "real_mean")):  # fmt: skip
            if isinstance(source.get(field), (int, float)):
                entry[key] = float(source[field])
    return fidelity


def read_results(path: Path) -> dict:
    """A `u4d experiment` results.json, checked for what this report reads; an InputError naming the file else."""
    results = read_json_file(path, "the results.json of `u4d experiment`")
    if not isinstance(results, dict) or not isinstance(results.get("arms"), list):
        raise InputError(f"{path}: expected a `u4d experiment` results.json, an object with an 'arms' list")
    for i, entry in enumerate(results["arms"]):
        where = f"{path}: arms[{i}]"
        if not isinstance(entry, dict) or not all(isinstance(entry.get(k), str) for k in ("arm", "backbone", "status")):
            raise InputError(f"{where}: expected an object with the strings 'arm', 'backbone' and 'status'")
        check_plain_name(entry["arm"], f"{where}: the arm name")  # it names the copied reliability figure
        runs = entry.get("runs", [])
        if entry["status"] in FINISHED and (not isinstance(runs, list) or not runs):
            raise InputError(f"{where} ({entry['arm']}): status {entry['status']!r} but no 'runs' list")
        for j, run in enumerate(runs if isinstance(runs, list) else []):
            if not isinstance(run, dict) or not isinstance(run.get("seed"), int):
                raise InputError(f"{where}.runs[{j}]: expected an object with an integer 'seed'")
    return results


def select_backbone(results: dict, backbone: str | None, path: Path, setting: str) -> tuple[str, list[dict]]:
    """The backbone's arm entries (the file's only backbone when the setting names none)."""
    backbones = list(dict.fromkeys(e["backbone"] for e in results["arms"]))
    if backbone is None:
        if len(backbones) != 1:
            raise InputError(f"{path}: holds the backbones {backbones}; name the setting {setting}/BACKBONE")
        backbone = backbones[0]
    if backbone not in backbones:
        have = ", ".join(backbones) or "no arm"
        raise InputError(f"{path}: no arm with backbone {backbone!r} (setting {setting!r}); the file has {have}")
    return backbone, [e for e in results["arms"] if e["backbone"] == backbone]


def rename_arms(entries: list[dict], renames: dict[str, str], path: Path) -> list[dict]:
    """The entries with --rename applied; an unfinished arm already called NEW gives way, a finished one is an error."""
    targets = {renames[e["arm"]] for e in entries if e["arm"] in renames}
    kept = []
    for e in entries:
        if e["arm"] not in renames and e["arm"] in targets:
            if e["status"] in FINISHED:
                raise InputError(
                    f"{path}: --rename gives a second arm the name {e['arm']!r} of a finished arm; rename that one "
                    f"too (--rename {e['arm']}={e['arm']}-old)"
                )
            continue
        kept.append({**e, "arm": renames.get(e["arm"], e["arm"])})
    names = [e["arm"] for e in kept]
    twice = next((name for name in names if names.count(name) > 1), None)
    if twice is not None:
        raise InputError(f"{path}: two arms are called {twice!r} after --rename")
    return kept


# ------------------------------------------------------------------------------------------------- numbers


def percent(stat: dict | None) -> dict | None:
    """A mean_std / paired_differences dict with its fractions in percent (mean, std, per_seed, ci95)."""
    if stat is None:
        return None
    scaled = dict(stat)
    for key in ("mean", "std"):
        if scaled.get(key) is not None:
            scaled[key] = 100 * scaled[key]
    if "per_seed" in scaled:
        scaled["per_seed"] = [None if v is None else 100 * v for v in scaled["per_seed"]]
    if scaled.get("ci95") is not None:
        scaled["ci95"] = [100 * v for v in scaled["ci95"]]
    return scaled


def is_finished(entry: dict) -> bool:
    """Whether an arm entry has finished runs to report."""
    return entry["status"] in FINISHED and bool(entry.get("runs"))


def arm_summary(entry: dict) -> dict:
    """One arm in percent: results.json's mean ± std over seeds plus the per-seed values; status alone if unfinished."""
    summary = {"status": entry["status"], "mode": entry.get("mode"), "bank": entry.get("bank")}
    if not is_finished(entry):
        return {**summary, "reason": entry.get("reason", "no finished run")}
    runs = sorted(entry["runs"], key=lambda r: r["seed"])
    summary["seeds"] = [r["seed"] for r in runs]
    for key, source in (*ARM_METRICS, ("wall_clock_s", "wall_clock_s")):
        values = [r.get(source) for r in runs]
        stat = {**(entry.get(source) or mean_std(values)), "per_seed": values}  # the stored aggregate when there
        summary[key] = stat if key == "wall_clock_s" else percent(stat)
    summary["iou"] = {name: percent(stat) for name, stat in (entry.get("iou") or {}).items()}
    summary["bands"] = {name: percent(stat) for name, stat in (entry.get("bands") or {}).items()}
    summary["provenance"] = [run_provenance(r) for r in runs]
    return summary


def run_provenance(run: dict) -> dict:
    """Where one run trained, its budget (steps; training minutes incl. a shared burn-in and resumes, from its log),
    the burn-in it started from and the bank scans it read (from its record; None if unknown: a run folder without a
    record)."""
    host = run.get("host") or {}
    banks = run.get("banks") or []
    wall = run.get("wall_clock_s")
    return {
        "seed": run["seed"],
        "cpu": host.get("cpu"),
        "torch": host.get("torch"),
        "steps": run.get("step"),
        "minutes": None if wall is None else round(wall / 60, 1),
        "burn_in_weights": run.get("burn_in_weights"),
        "bank_content": [bank.get("content_sha256") for bank in banks] or None,
    }


def burn_in_mismatches(arm: dict, reference: dict) -> list[int]:
    """Seeds at which both runs name their burn-in weights and the two differ (trained apart, e.g. on two machines:
    the pair then shares its label split and seed but not its first steps)."""
    ours = {p["seed"]: p["burn_in_weights"] for p in arm.get("provenance", [])}
    theirs = {p["seed"]: p["burn_in_weights"] for p in reference.get("provenance", [])}
    return sorted(s for s in ours.keys() & theirs.keys() if ours[s] and theirs[s] and ours[s] != theirs[s])


def pair_names(names: list[str]) -> list[tuple[str, str]]:
    """(arm, reference) pairs: NAMED_PAIRS, then every mean-teacher arm against each of REFERENCES, without reverses."""
    others = [(arm, ref) for ref in REFERENCES if ref in names for arm in names if arm not in (ref, "sup-only")]
    present = [pair for pair in PRESENT_PAIRS if all(name in names for name in pair)]
    wanted = [*NAMED_PAIRS, *present, *others]
    pairs: list[tuple[str, str]] = []
    for pair in wanted:
        if pair not in pairs and pair[::-1] not in pairs:
            pairs.append(pair)
    return pairs


def paired_summary(entries: list[dict]) -> tuple[dict, dict]:
    """Seed-paired differences arm - reference in points for every pair of `pair_names`, and why others have none."""
    by_name = {e["arm"]: e for e in entries}
    paired, unpaired = {}, {}
    for arm, reference in pair_names(list(by_name)):
        key = f"{arm}_vs_{reference}"
        absent = [name for name in (arm, reference) if name not in by_name]
        if absent:
            unpaired[key] = f"{' and '.join(absent)} not in results.json"
            continue
        unfinished = [
            f"{name} {by_name[name]['status']}" for name in (arm, reference) if not is_finished(by_name[name])
        ]
        if unfinished:
            unpaired[key] = ", ".join(unfinished)
            continue
        diff = paired_arms(by_name[reference], by_name[arm])
        if diff["miou"]["n"] == 0:
            unpaired[key] = "no seed finished in both"
            continue
        miou = percent(diff["miou"])
        paired[key] = {
            "arm": arm,
            "reference": reference,
            "mean": miou["mean"],
            "ci95": miou["ci95"],
            "p": miou["p"],
            "miou": miou,
            "ece": percent(diff["ece_per_scan"]),
            "iou": {name: percent(stat) for name, stat in diff["iou"].items()},
            "bands": {name: percent(stat) for name, stat in diff["bands"].items()},
        }
    return paired, unpaired


CEILING, BASE = "mt+real", "mt"  # the ceiling arm (real scans of unused places) and the arm it adds them to
BOOTSTRAP_DRAWS = 10_000


def ceiling_share(arm: dict, ceiling: dict, base: dict, draws: int = BOOTSTRAP_DRAWS, seed: int = 0) -> dict | None:
    """Share of the ceiling's mIoU gain a bank recovers, (bank − mt) / (real − mt), with the means over the seeds all
    three arms finished; ci95: percentile bootstrap over those seeds (each draw resamples seeds, pairs kept);
    unresolved: the share of draws whose ceiling gain is <= 0 (the ratio has no meaning there). None below 2 seeds."""
    values = {}
    for name, entry in (("arm", arm), ("ceiling", ceiling), ("base", base)):
        values[name] = dict(zip(entry.get("seeds", []), entry.get("miou", {}).get("per_seed", []), strict=True))
    seeds = sorted(set.intersection(*(set(k for k, v in d.items() if v is not None) for d in values.values())))
    if len(seeds) < 2:
        return None
    gain = np.array([values["arm"][k] - values["base"][k] for k in seeds])  # (S,) points
    ceiling_gain = np.array([values["ceiling"][k] - values["base"][k] for k in seeds])  # (S,)
    picks = np.random.default_rng(seed).integers(0, len(seeds), size=(draws, len(seeds)))  # (D, S)
    numerators, denominators = gain[picks].mean(1), ceiling_gain[picks].mean(1)  # (D,)
    valid = denominators > 0
    ratios = numerators[valid] / denominators[valid]
    return {
        "seeds": seeds,
        "share": float(gain.mean() / ceiling_gain.mean()) if ceiling_gain.mean() > 0 else None,
        "gain": float(gain.mean()),
        "ceiling_gain": float(ceiling_gain.mean()),
        "ci95": [float(q) for q in np.percentile(ratios, [2.5, 97.5])] if valid.any() else None,
        "unresolved": float(1 - valid.mean()),
        "draws": draws,
    }


def ceiling_shares(arms: dict) -> dict:
    """{ARM: ceiling_share} for every finished bank arm other than the ceiling, when the ceiling and mt finished."""
    if not all(arms.get(name, {}).get("status") in FINISHED for name in (CEILING, BASE)):
        return {}
    shares = {}
    for name, arm in arms.items():
        if arm.get("bank") and not name.startswith(CEILING) and arm["status"] in FINISHED:
            share = ceiling_share(arm, arms[CEILING], arms[BASE])
            if share is not None:
                shares[name] = share
    return shares


def setting_summary(
    results: dict, backbone: str, entries: list[dict], source: Path, renamed: dict, fidelity: dict | None = None
) -> dict:
    """One setting's block of summary.json (without its figures); `fidelity` {bank: ...} of `read_bank_evals`."""
    paired, unpaired = paired_summary(entries)
    arms = {e["arm"]: arm_summary(e) for e in entries}
    for pair in paired.values():
        pair["burn_in_differs"] = burn_in_mismatches(arms[pair["arm"]], arms[pair["reference"]])
    for arm in arms.values():
        bank = str(arm.get("bank") or "").rstrip("/")
        if bank and bank in (fidelity or {}):
            arm["bank_fidelity"] = fidelity[bank]
    return {
        "source": str(source),
        "backbone": backbone,
        "final_eval": bool((results.get("config") or {}).get("final_eval", False)),
        "seeds": sorted({seed for e in entries if is_finished(e) for seed in (r["seed"] for r in e["runs"])}),
        "config_seeds": (results.get("config") or {}).get("seeds"),
        "renamed": renamed,
        "units": "percent (points for differences); wall_clock_s in seconds",
        "arms": arms,
        "paired": paired,
        "unpaired": unpaired,
        "ceiling_share": ceiling_shares(arms),
    }


# ------------------------------------------------------------------------------------------------- report.md


def per_seed_text(values: list, signed: bool = False) -> str:
    """'47.05, 44.03' ('-' for a missing value)."""
    return ", ".join("-" if v is None else (f"{v:+.2f}" if signed else f"{v:.2f}") for v in values)


def needed_text(stat: dict) -> str:
    """Seeds a paired t-test at 95 % would need for this mean and spread."""
    if stat["n"] < 2 or stat["mean"] == 0:
        return "n/a"
    return str(stat["seeds_needed"]) if stat["seeds_needed"] is not None else f"> {MAX_SEEDS_ESTIMATE}"


def noise_text(stat: dict, metric: str, arm: str) -> str:
    """Whether a paired difference (points) is inside the seed noise, i.e. its 95 % CI contains 0, in words."""
    if stat["n"] == 0:
        return f"{metric}: no seed where both arms have it"
    if stat["n"] == 1:
        return (
            f"{metric} {stat['mean']:+.2f} points on the one seed both finished ({stat['seeds'][0]}): no confidence "
            "interval, so it cannot be told from seed noise"
        )
    lo, hi = stat["ci95"]
    p_text = "n/a (the same difference on every seed)" if stat["p"] is None else f"{stat['p']:.2g}"
    head = (
        f"{metric} {stat['mean']:+.2f} ± {stat['std']:.2f} points over {stat['n']} seeds, 95 % CI "
        f"[{lo:+.2f}, {hi:+.2f}], p = {p_text}"
    )
    if not lo <= 0 <= hi:
        return f"{head}: the CI excludes 0, outside the seed noise ({arm} {'higher' if stat['mean'] > 0 else 'lower'})"
    if stat["mean"] == 0:
        return f"{head}: no difference"
    more = (
        f"more than {MAX_SEEDS_ESTIMATE} paired seeds"
        if stat["seeds_needed"] is None
        else f"about {stat['seeds_needed']} paired seeds"
    )
    return f"{head}: the CI contains 0, inside the seed noise ({more} would resolve a difference this size)"


def arms_table(arms: dict) -> list[str]:
    """The per-arm table of one setting."""
    lines = [
        "| arm | status | seeds | mIoU % | mIoU per seed | ECE per scan % | ECE per scan per seed | ECE pooled % "
        "| wall-clock per run, min |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, arm in arms.items():
        if "reason" in arm:
            lines.append(f"| {name} | {arm['status']}: {arm['reason']} | - | - | - | - | - | - | - |")
            continue
        lines.append(
            f"| {name} | {arm['status']} | {', '.join(map(str, arm['seeds']))} | {mean_text(arm['miou'])} | "
            f"{per_seed_text(arm['miou']['per_seed'])} | {mean_text(arm['ece'])} | "
            f"{per_seed_text(arm['ece']['per_seed'])} | {mean_text(arm['ece_pooled'])} | "
            f"{mean_text(arm['wall_clock_s'], scale=1 / 60, digits=1)} |"
        )
    return lines


def paired_table(paired: dict, metric: str) -> list[str]:
    """The paired-differences table of one metric ('miou' or 'ece')."""
    lines = [
        "| arm − reference | seeds | per seed | mean ± std | 95 % CI | p | seeds for p < 0.05 |",
        "|---|---|---|---|---|---|---|",
    ]
    for pair in paired.values():
        stat = pair[metric]
        ci = "n/a" if stat["ci95"] is None else f"[{stat['ci95'][0]:+.2f}, {stat['ci95'][1]:+.2f}]"
        p_text = "n/a" if stat["p"] is None else f"{stat['p']:.2g}"
        lines.append(
            f"| {pair['arm']} − {pair['reference']} | {', '.join(map(str, stat['seeds']))} | "
            f"{per_seed_text(stat['per_seed'], signed=True)} | {mean_text(stat, signed=True)} | {ci} | {p_text} | "
            f"{needed_text(stat)} |"
        )
    return lines


def starred(stat: dict | None) -> str:
    """A mean difference in points, '*' when its 95 % CI excludes 0."""
    if stat is None or stat["mean"] is None:
        return "n/a"
    ci = stat.get("ci95")
    return f"{stat['mean']:+.2f}" + ("*" if ci is not None and (ci[0] > 0 or ci[1] < 0) else "")


def difference_table(paired: dict, keys: list[str], field: str) -> list[str]:
    """Rows = classes or bands (`field` 'iou' or 'bands'), one column of mean differences per pair."""
    rows = list(dict.fromkeys(name for key in keys for name in paired[key][field]))
    counts = [paired[key]["miou"]["n"] for key in keys]
    head = [f"{paired[k]['arm']} − {paired[k]['reference']} ({n} seed{'s' * (n > 1)})" for k, n in zip(keys, counts)]
    lines = [f"| {'class' if field == 'iou' else 'distance'} | " + " | ".join(head) + " |"]
    lines.append("|---|" + "---|" * len(keys))
    lines += [f"| {row} | " + " | ".join(starred(paired[key][field].get(row)) for key in keys) + " |" for row in rows]
    return lines


BANK_COLUMNS = (("jsd", "BEV JSD", 3), ("mmd", "BEV MMD x1e4", 1), ("rangejs", "range JS", 3),
                ("intensityjs", "intensity JS", 3), ("frd", "FRD", 0), ("fpd", "FPD", 1))  # fmt: skip


def provenance_table(arms: dict) -> list[str]:
    """Per seed and arm: the host, the burn-in weights and the bank scans (runs with a record; else empty)."""
    rows = [(name, p) for name, arm in arms.items() for p in arm.get("provenance", []) if p["cpu"] is not None]
    if not rows:
        return []
    lines = ["", "### Where each run trained and its budget (from its record)", "",
             "Minutes: training time from the run's log, incl. the burn-in a mean-teacher arm shares with sup-only"
             " and time before a resume (one thread per run); not the final evaluation.", "",
             "| seed | arm | cpu | torch | steps | minutes | burn-in weights | bank scans |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, p in sorted(rows, key=lambda row: (row[1]["seed"], list(arms).index(row[0]))):
        bank = ", ".join(str(digest) for digest in p["bank_content"]) if p["bank_content"] else "-"
        steps = "-" if p.get("steps") is None else f"{p['steps']:,}"
        minutes = "-" if p.get("minutes") is None else f"{p['minutes']:.1f}"
        lines.append(
            f"| {p['seed']} | {name} | {p['cpu']} | {p['torch']} | {steps} | {minutes} | "
            f"{p['burn_in_weights'] or '-'} | {bank} |"
        )
    return lines


def bank_table(arms: dict) -> list[str]:
    """The banks the arms read, as `u4d evaluate` scored them against real scans (empty without --bank-eval)."""
    rows = [(name, arm["bank"], arm["bank_fidelity"]) for name, arm in arms.items() if "bank_fidelity" in arm]
    if not rows:
        return []
    columns = [c for c in BANK_COLUMNS if any(c[0] in f for _, _, f in rows)]
    lines = [
        "### The banks against real scans (`u4d evaluate`; lower = closer)",
        "",
        "| arm | bank | "
        + " | ".join(label for _, label, _ in columns)
        + " | points / scan (real) | intensity mean (real) |",
        "|---|---|" + "---|" * (len(columns) + 2),
    ]
    for name, bank, f in rows:
        cells = [f"{f[key]:.{digits}f}" if key in f else "-" for key, _, digits in columns]
        points = f"{f['points']:,.0f} ({f['real_points']:,.0f})" if "points" in f and "real_points" in f else "-"
        mean = f"{f['intensity_mean']:.3f} ({f['real_intensity_mean']:.3f})" if "intensity_mean" in f else "-"
        lines.append(f"| {name} | {bank} | " + " | ".join(cells) + f" | {points} | {mean} |")
    real = rows[0][2].get("real") or {}
    lines += ["", f"Real reference: `{real.get('root')}` sequences {', '.join(real.get('sequences') or [])}.", ""]
    return lines


def ceiling_table(shares: dict, arms: dict) -> list[str]:
    """The share of the ceiling's gain each bank recovers (with its bootstrap CI), or why there is none."""
    lines = ["", f"### Share of the ceiling's gain ({CEILING} − {BASE}) each bank recovers", ""]
    if CEILING not in arms:
        return lines + [f"Absent: no {CEILING} arm in this setting."]
    if not shares:
        return lines + [f"Absent: no bank arm finished 2 or more seeds together with {CEILING} and {BASE}."]
    lines += ["| bank arm | seeds | gain (points) | ceiling gain (points) | share | 95 % CI (bootstrap) | "
              "draws with ceiling gain <= 0 |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, c in shares.items():
        share = "n/a (ceiling gain <= 0)" if c["share"] is None else f"{100 * c['share']:.0f} %"
        ci = "n/a" if c["ci95"] is None else f"[{100 * c['ci95'][0]:.0f} %, {100 * c['ci95'][1]:.0f} %]"
        lines.append(f"| {name} | {len(c['seeds'])} | {c['gain']:+.2f} | {c['ceiling_gain']:+.2f} | {share} | {ci} | "
                     f"{100 * c['unresolved']:.0f} % |")  # fmt: skip
    return lines


def setting_markdown(name: str, s: dict) -> list[str]:
    """report.md's section of one setting."""
    evaluated = "full evaluation of each model.pt" if s["final_eval"] else "the runs' last periodic evaluation"
    renamed = "".join(f"; {old} reported as {new}" for old, new in s["renamed"].items())
    lines = [f"## {name}", "", f"`{s['source']}`, backbone {s['backbone']}, {evaluated}{renamed}.", ""]
    lines += ["### Arms (%, mean ± std over seeds)", "", *arms_table(s["arms"]), ""]
    lines += bank_table(s["arms"])
    paired, figures = s["paired"], s["figures"]
    lines += ["### Paired by seed (points, arm − reference on the seeds both finished)", ""]
    if paired:
        lines += ["p: two-sided paired t-test; seeds for p < 0.05: paired seeds at which this mean and spread would "]
        lines[-1] += "reach it (`experiment.seeds_needed`)."
        lines += ["", "mIoU:", "", *paired_table(paired, "miou"), "", "ECE per scan (lower = better calibrated):", ""]
        lines += [*paired_table(paired, "ece"), ""]
        lines += [
            f"- **{p['arm']} − {p['reference']}**: {noise_text(p['miou'], 'mIoU', p['arm'])}; "
            f"{noise_text(p['ece'], 'ECE per scan', p['arm'])}."
            for p in paired.values()
        ]
        apart = [f"{p['arm']} − {p['reference']} (seeds {', '.join(map(str, p['burn_in_differs']))})"
                 for p in paired.values() if p.get("burn_in_differs")]  # fmt: skip
        if apart:
            note = "Pairs whose two runs started from different burn-in weights (trained apart, e.g. on two machines: "
            lines += ["", note + "same label split and seed, not the same first steps): " + "; ".join(apart) + "."]
    else:
        lines.append("No pair of arms has a seed finished in both.")
    if s["unpaired"]:
        lines += [
            "",
            "Not compared: " + "; ".join(f"{k.replace('_vs_', ' − ')} ({v})" for k, v in s["unpaired"].items()),
        ]
    lines += ceiling_table(s.get("ceiling_share", {}), s["arms"])
    class_keys = [f"{a}_vs_{b}" for a, b in CLASS_PAIRS if f"{a}_vs_{b}" in paired]
    lines += ["", "### Per-class IoU differences (points, mean over the common seeds; * = 95 % CI excludes 0)", ""]
    if class_keys:
        lines += difference_table(paired, class_keys, "iou")
    else:
        pairs = ", ".join(f"{a} − {b}" for a, b in CLASS_PAIRS)
        lines.append(f"Absent: none of {pairs} has a seed finished in both arms.")
    band_keys = [key for key, pair in paired.items() if any(b["mean"] is not None for b in pair["bands"].values())]
    lines += ["", "### mIoU differences by distance from the sensor (points; * = 95 % CI excludes 0)", ""]
    if band_keys:
        lines += difference_table(paired, band_keys, "bands")
    else:
        lines.append(
            "Absent: the runs carry no distance-band metrics (a full evaluation, `final_eval: true`, adds them)."
        )
    lines += provenance_table(s["arms"])
    lines += ["", "### Figures", ""]
    for label, key in (("paired differences", "paired"), ("per-class IoU differences", "per_class")):
        lines.append(f"- {label}: " + (f"[{figures[key]}]({figures[key]})" if figures[key] else "not drawn (no data)"))
    curves = figures["learning_curves"]
    lines.append("- learning curves: " + (f"[{curves}]({curves})" if curves else "not in results.json"))
    reliability = ", ".join(f"[{arm}]({png})" for arm, png in figures["reliability"].items())
    lines.append("- reliability diagrams (bins pooled over seeds): " + (reliability or "none in results.json"))
    if figures["not_found"]:
        lines.append(f"- named in results.json but not found beside it: {', '.join(figures['not_found'])}")
    return lines + [""]


def report_markdown(summary: dict, command: str) -> str:
    """report.md: per setting the arms, the paired differences with their noise verdicts, per class and band."""
    lines = [
        "# Downstream comparison: MT + LaserMix with and without generated banks",
        "",
        f"Generated by `{command}` from the results.json of `u4d experiment` (do not edit by hand).",
        "mIoU and ECE in %; ECE per scan as in Calib3D (mean of per-scan ECEs), pooled over all points. Differences "
        "are paired by seed, in points; a difference whose 95 % CI contains 0 is inside the seed-to-seed noise.",
        "",
    ]
    for name, setting in summary.items():
        lines += setting_markdown(name, setting)
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------- figures


def save_figure(fig: Figure, path: Path) -> None:
    """PNG through the Agg canvas, written atomically."""
    FigureCanvasAgg(fig)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=120)


def plot_paired_ci(paired: dict, path: Path, title: str) -> None:
    """Per pair and metric: a dot per seed, the mean (diamond) and its 95 % CI (bar), the zero line."""
    names = list(paired)
    fig = Figure(figsize=(10, 1.4 + 0.45 * len(names)))
    axes = fig.subplots(1, 2, sharey=True)
    for ax, (metric, label) in zip(axes, (("miou", "mIoU"), ("ece", "ECE per scan"))):
        for row, name in enumerate(names):
            stat = paired[name][metric]
            if stat["mean"] is None:
                continue
            ax.scatter(stat["per_seed"], [row - 0.15] * len(stat["per_seed"]), s=16, color="tab:blue", zorder=3)
            ci = stat["ci95"]
            xerr = None if ci is None else [[stat["mean"] - ci[0]], [ci[1] - stat["mean"]]]
            ax.errorbar(stat["mean"], row + 0.1, xerr=xerr, fmt="D", color="black", markersize=4, capsize=3)
        ax.axvline(0.0, color="tab:red", linewidth=1)
        ax.set_xlabel(f"{label} difference (points)")
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(range(len(names)), [name.replace("_vs_", " − ") for name in names], fontsize=8)
    axes[0].set_ylim(len(names) - 0.5, -0.5)
    fig.suptitle(f"{title}: dots = seeds, diamond = mean, bar = 95 % CI", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def plot_class_differences(paired: dict, keys: list[str], path: Path, title: str) -> None:
    """Per-class IoU difference bars (points) of the pairs `keys`, 95 % CI whiskers where there are 2+ seeds."""
    classes = list(dict.fromkeys(name for key in keys for name in paired[key]["iou"]))
    x, width = np.arange(len(classes)), 0.8 / len(keys)
    fig = Figure(figsize=(max(6.0, 2 + 0.45 * len(classes)), 4))
    ax = fig.subplots()
    for i, key in enumerate(keys):
        stats = [paired[key]["iou"].get(name) or {"mean": None} for name in classes]
        means = np.array([np.nan if s["mean"] is None else s["mean"] for s in stats])
        err = np.array(
            [[m - s["ci95"][0], s["ci95"][1] - m] if s.get("ci95") else [0, 0] for s, m in zip(stats, means)]
        )
        ax.bar(
            x + (i - (len(keys) - 1) / 2) * width, means, width, yerr=err.T, capsize=2, label=key.replace("_vs_", " − ")
        )
    ax.axhline(0.0, color="black", linewidth=0.8)
    ax.set_xticks(x, classes, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("IoU difference (points)")
    ax.set_title(f"{title}: per-class IoU, mean over common seeds, 95 % CI", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def copy_figure(source: Path, target: Path) -> bool:
    """Copy a PNG atomically; False when the source is missing."""
    if not source.is_file():
        return False
    atomic_write_bytes(target, source.read_bytes())
    return True


def write_figures(s: dict, results: dict, entries: list[dict], source_dir: Path, out: Path, title: str) -> dict:
    """Draw one setting's paired and per-class figures and copy its experiment's PNGs; their names in `out`."""
    prefix = title.replace("/", "_")
    figures: dict = {"paired": None, "per_class": None, "learning_curves": None, "reliability": {}, "not_found": []}
    if s["paired"]:
        figures["paired"] = f"{prefix}_paired.png"
        plot_paired_ci(s["paired"], out / figures["paired"], title)
    class_keys = [f"{a}_vs_{b}" for a, b in CLASS_PAIRS if f"{a}_vs_{b}" in s["paired"]]
    if class_keys and any(s["paired"][key]["iou"] for key in class_keys):
        figures["per_class"] = f"{prefix}_per_class.png"
        plot_class_differences(s["paired"], class_keys, out / figures["per_class"], title)
    named = [(e.get("reliability_png"), f"{prefix}_reliability_{e['arm']}.png", e["arm"]) for e in entries]
    curves = results.get(f"learning_curves_png_{s['backbone']}")
    named += [(curves, f"{prefix}_learning_curves.png", None)] if curves else []
    for name, target, arm in named:
        if not name:
            continue
        if not copy_figure(source_dir / Path(name).name, out / target):
            figures["not_found"].append(name)
        elif arm is None:
            figures["learning_curves"] = target
        else:
            figures["reliability"][arm] = target
    return figures


# ------------------------------------------------------------------------------------------------- CLI


def run(argv: list[str] | None = None) -> int:
    """Read every setting (all checked before anything is written), then write summary.json, report.md, figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--setting", action="append", required=True, metavar="NAME=PATH", help=f"e.g. {EXAMPLE}")
    parser.add_argument("--rename", action="append", default=[], metavar="OLD=NEW", help="rename an arm in every file")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder")
    parser.add_argument(
        "--bank-eval", action="append", default=[], metavar="BANK=DIR",
        help="a bank's `u4d evaluate --json` folder, e.g. banks/u4d_hdl64=runs/eval_u4d (repeatable)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    renames = parse_renames(args.rename)
    fidelity = read_bank_evals(args.bank_eval)
    settings = [parse_setting(text) for text in args.setting]
    names = [name for name, _, _ in settings]
    if len(set(names)) != len(names):
        raise InputError(f"--setting: the names {names} are not distinct")
    loaded, used = [], set()
    for name, backbone, path in settings:
        results = read_results(path)
        backbone, entries = select_backbone(results, backbone, path, name)
        renamed = {e["arm"]: renames[e["arm"]] for e in entries if e["arm"] in renames}
        used |= set(renamed)
        loaded.append((name, backbone, path, results, rename_arms(entries, renames, path), renamed))
    unused = [old for old in renames if old not in used]
    if unused:
        raise InputError(f"--rename {unused[0]}={renames[unused[0]]}: no setting has an arm {unused[0]!r}")
    read_banks = {str(e.get("bank") or "").rstrip("/") for *_, entries, _ in loaded for e in entries}
    stray = [bank for bank in fidelity if bank not in read_banks]
    if stray:
        known = ", ".join(sorted(b for b in read_banks if b)) or "none"
        raise InputError(f"--bank-eval {stray[0]}=...: no arm reads that bank (the arms' banks: {known})")
    out = make_folder(args.out)
    summary = {}
    for name, backbone, path, results, entries, renamed in loaded:
        setting = setting_summary(results, backbone, entries, path, renamed, fidelity)
        setting["figures"] = write_figures(setting, results, entries, path.parent, out, name)
        summary[name] = setting
    command = shlex.join(["python", "benchmarks/downstream_report.py", *(sys.argv[1:] if argv is None else argv)])
    atomic_write_json(out / "summary.json", summary)
    atomic_write_text(out / "report.md", report_markdown(summary, command))
    print(f"-> {out / 'summary.json'}, {out / 'report.md'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with bad input (a file, a --setting) as a one-line error and exit code 2."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
