"""Sim-to-real transfer: a segmentor trained on one simulated world, scored on the labelled real scans.

    python benchmarks/reports/transfer_table.py --runs ../runs/transfer --worlds seg_rich varied \
        --out benchmarks/results/world/sim_to_real_transfer

Reads RUNS/WORLD_sSEED/eval_real.json (the real SemanticKITTI scans) and eval_sim.json (held-out simulated places),
both `u4d seg-eval --json` outputs (segmentation/evaluate.py `summary_of`); the first world is "before", the last
"after". Seeds are the WORLD_sN folders found for any world (or --seeds); a world/seed without its json is listed as
not measured, never dropped. Nothing is recomputed from predictions. Writes OUT.json, OUT.md and OUT_confusion.png
(one row-normalised real confusion per world, summed over seeds) and prints OUT.md.

OUT.json, every metric in percent (points for differences); `per_seed` lists are aligned with the `seeds` beside them
(null where a seed is not measured); std is the sample std (ddof 1), null below 2 seeds:
    command, runs, before, after, seeds, classes_present (classes with real ground-truth points in some file)
    worlds.WORLD: role, measured_real / measured_sim (seeds),
        real: miou_present / ece_per_scan / ece_pooled: {mean, std, n, per_seed}, num_scans: [per seed],
            iou.CLASS (mean over seeds, present classes only),
            confusion: {rows, columns, points, percent} (rows = present ground-truth classes, summed over seeds;
                columns = the same classes and "other" = predictions of classes absent from the real ground truth)
        sim: miou: {mean, std, n, per_seed}
    paired.AFTER_vs_BEFORE (AFTER - BEFORE on the seeds measured in both): miou_present / ece_per_scan: {seeds,
        per_seed, mean, std, n, ci95 [lo, hi] (t distribution), p (two-sided paired t-test), ...}, unpaired_seeds
        {seed: why it is left out}
    goals: [{goal, metric, target, worlds.WORLD: {mean, met (by the mean), seeds_met, n}}]
    missing: [{world, seed, file, reason}]
    figures.confusion: the PNG's file name
"""

from __future__ import annotations

import argparse
import math
import re
import shlex
import sys
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from segmentation.experiment import mean_std, paired_differences
from segmentation.metrics import confusion_shares
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import atomic_open, atomic_write_json, atomic_write_text, make_folder, read_json_file
from u4d_aug.validate import check_plain_name

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "results" / "world" / "sim_to_real_transfer"
DEFAULT_WORLDS = ("seg_rich", "varied")
REAL_FILE, SIM_FILE = "eval_real.json", "eval_sim.json"
REAL_KEYS = ("miou_present", "ece_per_scan", "ece_pooled", "iou", "confusion")  # what this table reads
SIM_KEYS = ("miou",)
PAIRED_METRICS = ("miou_present", "ece_per_scan")
GOALS = (  # the targets on the real scans: (metric, label, target in %, higher is better)
    ("miou_present", "real mIoU over present classes ≥ 50 %", 50.0, True),
    ("ece_per_scan", "real ECE per scan ≤ 5 %", 5.0, False),
)
OTHER = "other"  # the confusion column of predictions into classes absent from the real ground truth


# ------------------------------------------------------------------------------------------------- inputs


def _number(value: object, where: str) -> float | None:
    """A json number or null (a non-finite number becomes null); an InputError naming the field else."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: expected a number or null, got {value!r}")
    return float(value) if math.isfinite(value) else None


def read_seg_eval(path: Path, keys: tuple[str, ...]) -> dict:
    """A `u4d seg-eval --json` output holding `keys`; an InputError naming the file and the missing key else."""
    data = read_json_file(path, "the output of `u4d seg-eval --json`")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a json object (the output of `u4d seg-eval --json`)")
    absent = [key for key in keys if key not in data]
    if absent:
        names = ", ".join(repr(key) for key in absent)
        raise InputError(f"{path}: no key {names} (expected the output of `u4d seg-eval --json`)")
    return data


def read_real(path: Path) -> dict:
    """eval_real.json checked: the three fractions, iou {class: fraction or null} and its K x K confusion counts."""
    data = read_seg_eval(path, REAL_KEYS)
    real = {key: _number(data[key], f"{path}: {key}") for key in ("miou_present", "ece_per_scan", "ece_pooled")}
    if not isinstance(data["iou"], dict) or not data["iou"]:
        raise InputError(f"{path}: iou: expected an object {{class: IoU or null}}")
    real["iou"] = {str(name): _number(value, f"{path}: iou.{name}") for name, value in data["iou"].items()}
    k = len(real["iou"])
    confusion = data["confusion"]
    if (
        not isinstance(confusion, list)
        or len(confusion) != k
        or any(not isinstance(row, list) or len(row) != k for row in confusion)
    ):
        raise InputError(f"{path}: confusion: expected {k} x {k} point counts (rows and columns = the classes of iou)")
    counts = [value for row in confusion for value in row]
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 for v in counts):
        raise InputError(f"{path}: confusion: expected non-negative point counts")
    real["confusion"] = np.asarray(confusion, dtype=np.float64)  # (K, K) rows = ground truth, columns = prediction
    num_scans = data.get("num_scans")
    real["num_scans"] = num_scans if isinstance(num_scans, int) and not isinstance(num_scans, bool) else None
    return real


def read_sim(path: Path) -> dict:
    """eval_sim.json checked for its mIoU (fraction or null)."""
    return {"miou": _number(read_seg_eval(path, SIM_KEYS)["miou"], f"{path}: miou")}


def find_seeds(runs: Path, worlds: list[str]) -> list[int]:
    """The N of every WORLD_sN folder under `runs`, over all worlds, ascending."""
    patterns = [re.compile(re.escape(world) + r"_s(\d+)") for world in worlds]
    seeds = {
        int(m.group(1))
        for p in runs.iterdir()
        if p.is_dir()
        for pattern in patterns
        if (m := pattern.fullmatch(p.name))
    }
    return sorted(seeds)


def load_runs(runs: Path, worlds: list[str], seeds: list[int]) -> tuple[dict, list[dict]]:
    """{world: {seed: {"real": dict | None, "sim": dict | None}}} and what is not measured (world, seed, file, why)."""
    loaded: dict = {world: {} for world in worlds}
    missing = []
    for world in worlds:
        for seed in seeds:
            folder = runs / f"{world}_s{seed}"
            entry = {}
            for part, name, read in (("real", REAL_FILE, read_real), ("sim", SIM_FILE, read_sim)):
                path = folder / name
                entry[part] = read(path) if path.is_file() else None
                if entry[part] is None:
                    reason = "not found" if folder.is_dir() else "no run folder"
                    missing.append({"world": world, "seed": seed, "file": str(path), "reason": reason})
            loaded[world][seed] = entry
    return loaded, missing


def check_same_classes(loaded: dict, runs: Path) -> list[str]:
    """The class names every eval_real.json shares (same names, same order), so that confusions can be summed."""
    classes, first = None, None
    for world, by_seed in loaded.items():
        for seed, entry in by_seed.items():
            if entry["real"] is None:
                continue
            names = list(entry["real"]["iou"])
            path = runs / f"{world}_s{seed}" / REAL_FILE
            if classes is None:
                classes, first = names, path
            elif names != classes:
                raise InputError(f"{path}: classes {names} differ from those of {first} ({classes})")
    return classes or []


# ------------------------------------------------------------------------------------------------- numbers


def percent_stat(values: list[float | None]) -> dict:
    """{mean, std (ddof 1; null below 2 values), n, per_seed} of fractions, in percent."""
    per_seed = [None if v is None else 100 * v for v in values]
    stat = mean_std(per_seed)
    if stat["n"] < 2:
        stat["std"] = None
    return {**stat, "per_seed": per_seed}


def confusion_block(matrix: np.ndarray, classes: list[str], present: np.ndarray) -> dict:
    """Rows = present ground-truth classes, columns = the same + OTHER (absent classes); points and row percent."""
    shares = confusion_shares(matrix)  # (K, K) each ground-truth row sums to 1
    rows = np.flatnonzero(present)
    absent = np.flatnonzero(~present)

    def present_and_other(m: np.ndarray) -> np.ndarray:
        return np.concatenate([m[np.ix_(rows, rows)], m[np.ix_(rows, absent)].sum(axis=1, keepdims=True)], axis=1)

    return {
        "rows": [classes[r] for r in rows],
        "columns": [classes[r] for r in rows] + [OTHER],
        "points": present_and_other(matrix).astype(np.int64).tolist(),
        "percent": (100 * present_and_other(shares)).tolist(),
    }


def world_summary(by_seed: dict, seeds: list[int], classes: list[str], present: np.ndarray) -> dict:
    """One world's real and sim numbers over `seeds` (percent) and its real confusion summed over the seeds."""
    reals = [by_seed[s]["real"] for s in seeds]
    sims = [by_seed[s]["sim"] for s in seeds]
    measured = [r for r in reals if r is not None]
    real: dict = {
        key: percent_stat([None if r is None else r[key] for r in reals])
        for key in ("miou_present", "ece_per_scan", "ece_pooled")
    }
    real["num_scans"] = [None if r is None else r["num_scans"] for r in reals]
    real["iou"] = {
        name: percent_stat([r["iou"][name] for r in measured])["mean"]
        for name, p in zip(classes, present)
        if p  # classes without real ground truth have no IoU to speak of
    }
    if measured:
        real["confusion"] = confusion_block(sum(r["confusion"] for r in measured), classes, present)
    return {
        "measured_real": [s for s, r in zip(seeds, reals) if r is not None],
        "measured_sim": [s for s, r in zip(seeds, sims) if r is not None],
        "real": real,
        "sim": {"miou": percent_stat([None if r is None else r["miou"] for r in sims])},
    }


def paired_summary(loaded: dict, before: str, after: str) -> dict:
    """after - before on the real scans, seed by seed (the seeds both measured), in points; why others are left out."""
    paired: dict = {}
    for key in PAIRED_METRICS:
        values = [
            {
                s: e["real"][key]
                for s, e in loaded[world].items()
                if e["real"] is not None and e["real"][key] is not None
            }
            for world in (before, after)
        ]
        diff = paired_differences(*values)  # other - reference: after - before
        paired[key] = {
            **diff,
            "per_seed": [100 * v for v in diff["per_seed"]],
            "mean": None if diff["mean"] is None else 100 * diff["mean"],
            "std": 100 * diff["std"] if diff["n"] >= 2 else None,  # mean_std gives 0 for one seed
            "ci95": None if diff["ci95"] is None else [100 * v for v in diff["ci95"]],
        }
    measured = {world: {s for s, e in loaded[world].items() if e["real"] is not None} for world in (before, after)}
    paired["unpaired_seeds"] = {
        str(s): f"only {world} measured"
        for world, other in ((before, after), (after, before))
        for s in sorted(measured[world] - measured[other])
    }
    return paired


def goal_summary(worlds: dict) -> list[dict]:
    """Each goal against every world's mean over seeds and against its single seeds."""
    goals = []
    for key, label, target, higher in GOALS:
        entry: dict = {"goal": label, "metric": key, "target": target, "worlds": {}}
        for world, summary in worlds.items():
            stat = summary["real"][key]
            values = [v for v in stat["per_seed"] if v is not None]
            meets = [v >= target if higher else v <= target for v in values]
            met = None if stat["mean"] is None else (stat["mean"] >= target if higher else stat["mean"] <= target)
            entry["worlds"][world] = {"mean": stat["mean"], "met": met, "seeds_met": sum(meets), "n": len(values)}
        goals.append(entry)
    return goals


def build_table(loaded: dict, missing: list[dict], worlds: list[str], seeds: list[int], classes: list[str]) -> dict:
    """OUT.json without `command` and `figures`."""
    matrices = [e["real"]["confusion"] for by_seed in loaded.values() for e in by_seed.values() if e["real"]]
    present = sum(matrices).sum(axis=1) > 0 if matrices else np.zeros(len(classes), dtype=bool)  # (K,)
    before, after = worlds[0], worlds[-1]
    summaries = {}
    for world in worlds:
        role = "before" if world == before else "after" if world == after else "compared with before"
        summaries[world] = {"role": role, **world_summary(loaded[world], seeds, classes, present)}
    return {
        "before": before,
        "after": after,
        "seeds": seeds,
        "classes_present": [name for name, p in zip(classes, present) if p],
        "worlds": summaries,
        "paired": {f"{world}_vs_{before}": paired_summary(loaded, before, world) for world in worlds[1:]},
        "goals": goal_summary(summaries),
        "missing": missing,
    }


# ------------------------------------------------------------------------------------------------- markdown


def pm(stat: dict, signed: bool = False) -> str:
    """'46.59 ± 1.89', '46.59 (1 seed)' or 'n/a'; '+' in front of a difference when `signed`."""
    if stat["mean"] is None:
        return "n/a"
    mean = f"{stat['mean']:{'+' if signed else ''}.2f}"
    return f"{mean} (1 seed)" if stat["std"] is None else f"{mean} ± {stat['std']:.2f}"


def seeds_text(values: list[float | None], seeds: list[int], signed: bool = False) -> str:
    """'s0 47.05, s1 -' per seed ('-' = not measured)."""
    return ", ".join(
        f"s{s} " + ("-" if v is None else f"{v:{'+' if signed else ''}.2f}") for s, v in zip(seeds, values)
    )


def worlds_table(table: dict) -> list[str]:
    """Per world: the real mIoU over present classes and ECEs, and the held-out sim mIoU (mean ± std over seeds)."""
    lines = [
        "| world | role | real mIoU present % | per seed | real ECE per scan % | per seed | real ECE pooled % "
        "| sim mIoU % (held-out) | real scans |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    seeds = table["seeds"]
    for world, w in table["worlds"].items():
        real = w["real"]
        scans = ", ".join(dict.fromkeys(str(n) for n in real["num_scans"] if n is not None)) or "-"
        miou, ece = real["miou_present"], real["ece_per_scan"]
        lines.append(
            f"| {world} | {w['role']} | {pm(miou)} | {seeds_text(miou['per_seed'], seeds)} | {pm(ece)} | "
            f"{seeds_text(ece['per_seed'], seeds)} | "
            f"{pm(real['ece_pooled'])} | {pm(w['sim']['miou'])} | {scans} |"
        )
    return lines


def paired_lines(paired: dict, before: str, after: str) -> list[str]:
    """The paired-differences table of one pair and which seeds it leaves out."""
    lines = [
        f"### {after} − {before}",
        "",
        "| metric | seeds | per seed | mean ± std | 95 % CI | p |",
        "|---|---|---|---|---|---|",
    ]
    for metric, label in (
        ("miou_present", "real mIoU present (points)"),
        ("ece_per_scan", "real ECE per scan (points)"),
    ):
        stat = paired[metric]
        ci = "n/a" if stat["ci95"] is None else f"[{stat['ci95'][0]:+.2f}, {stat['ci95'][1]:+.2f}]"
        p = "n/a" if stat["p"] is None else f"{stat['p']:.2g}"
        seeds = ", ".join(map(str, stat["seeds"])) or "none"
        lines.append(
            f"| {label} | {seeds} | {seeds_text(stat['per_seed'], stat['seeds'], True) or '-'} | "
            f"{pm(stat, True)} | {ci} | {p} |"
        )
    left_out = paired["unpaired_seeds"]
    lines.append("")
    if left_out:
        lines.append(
            "Paired only on the seeds measured in both worlds; left out: "
            + "; ".join(f"seed {s} ({why})" for s, why in left_out.items())
            + "."
        )
    else:
        lines.append("Every measured seed is measured in both worlds.")
    if paired["miou_present"]["n"] < 2:
        lines.append("Fewer than 2 paired seeds: no confidence interval and no p-value.")
    return lines


def goal_lines(goals: list[dict], worlds: dict) -> list[str]:
    """One line per goal, stated against each world's measured mean (and how many seeds meet it)."""
    lines = []
    for goal in goals:
        parts = []
        for world, g in goal["worlds"].items():
            role = worlds[world]["role"]
            if g["mean"] is None:
                parts.append(f"{world} ({role}) not measured")
                continue
            verdict = "met" if g["met"] else "not met"
            parts.append(f"{world} ({role}) {g['mean']:.2f} %: {verdict} ({g['seeds_met']} of {g['n']} seeds)")
        lines.append(f"- **{goal['goal']}**: " + "; ".join(parts) + ".")
    return lines


def class_table(table: dict) -> list[str]:
    """Per present class: the real IoU of each world (mean over its seeds) and last − first."""
    worlds, before, after = table["worlds"], table["before"], table["after"]
    head = [f"{world} ({w['role']}) %" for world, w in worlds.items()]
    lines = ["| class | " + " | ".join(head) + f" | {after} − {before} |", "|---|" + "---|" * (len(head) + 1)]
    for name in table["classes_present"]:
        means = [w["real"]["iou"].get(name) for w in worlds.values()]
        cells = ["n/a" if m is None else f"{m:.2f}" for m in means]
        first, last = worlds[before]["real"]["iou"].get(name), worlds[after]["real"]["iou"].get(name)
        diff = "n/a" if first is None or last is None else f"{last - first:+.2f}"
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {diff} |")
    return lines


def to_markdown(table: dict) -> str:
    """OUT.md: the worlds, the paired differences, the goals, the per-class IoU, the figure and what is missing."""
    before, after = table["before"], table["after"]
    lines = [
        "# Sim-to-real transfer: trained on a simulated world, scored on real scans",
        "",
        f"Generated by `{table['command']}` from the `u4d seg-eval --json` outputs under `{table['runs']}` "
        "(do not edit by hand).",
        "",
        f"A segmentor trained only on a simulated world, scored on the labelled real SemanticKITTI scans: before = "
        f"world `{before}`, after = world `{after}`. In %, mean ± std over seeds (sample std, ddof 1). Real mIoU "
        "over the classes with ground-truth points in the real scans; ECE per scan as in Calib3D (mean of per-scan "
        "ECEs), pooled over all points; sim mIoU on the world's own held-out places (eval_sim.json).",
        "",
        "## Per world",
        "",
        *worlds_table(table),
        "",
        "## Paired by seed (after − before, points)",
        "",
        "p: two-sided paired t-test; 95 % CI of the mean difference from the t distribution.",
        "",
    ]
    for key, paired in table["paired"].items():
        lines += [*paired_lines(paired, before, key.rsplit("_vs_", 1)[0]), ""]
    lines += [
        "## Goals (on the real scans, against the mean over seeds)",
        "",
        *goal_lines(table["goals"], table["worlds"]),
    ]
    lines += ["", "## Per-class IoU on the real scans (%, mean over seeds, classes with ground truth)", ""]
    lines += class_table(table) if table["classes_present"] else ["No real evaluation measured."]
    figure = table["figures"]["confusion"]
    lines += ["", "## Real confusion (summed over seeds, rows = ground truth, row-normalised %)", ""]
    lines += [f"![confusion]({figure})" if figure else "Not drawn: no real evaluation measured."]
    lines += ["", f"Column `{OTHER}`: points predicted as a class with no ground truth in the real scans.", ""]
    lines += ["## Not measured", ""]
    lines += [f"- {m['world']} seed {m['seed']}: `{m['file']}` {m['reason']}" for m in table["missing"]] or ["None."]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------- figure


def plot_confusions(table: dict, path: Path) -> None:
    """One row-normalised real confusion per world side by side (present classes + OTHER), values written in."""
    worlds = table["worlds"]
    k = len(table["classes_present"])
    fig = Figure(figsize=(len(worlds) * max(3.5, 1.6 + 0.45 * k), 2.4 + 0.4 * k))
    axes = np.atleast_1d(fig.subplots(1, len(worlds)))
    for ax, (world, w) in zip(axes, worlds.items()):
        confusion = w["real"].get("confusion")
        if confusion is None:
            ax.text(0.5, 0.5, "not measured", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
        else:
            shares = np.asarray(confusion["percent"])  # (present, present + 1)
            ax.imshow(shares, cmap="Blues", vmin=0, vmax=100)
            for r, c in zip(*np.nonzero(shares >= 0.5)):
                color = "white" if shares[r, c] > 60 else "black"
                ax.text(c, r, f"{shares[r, c]:.0f}", ha="center", va="center", fontsize=6, color=color)
            ax.set_xticks(range(len(confusion["columns"])), confusion["columns"], rotation=90, fontsize=7)
            ax.set_yticks(range(len(confusion["rows"])), confusion["rows"], fontsize=7)
            ax.set_xlabel("predicted")
            ax.set_ylabel("ground truth")
        seeds = len(w["measured_real"])
        mean = w["real"]["miou_present"]["mean"]
        miou = "" if mean is None else f", mIoU present {mean:.1f} %"
        ax.set_title(f"{w['role']}: {world}\n{seeds} seed{'s' * (seeds != 1)}{miou}", fontsize=9)
    fig.suptitle("real scans, % of each ground-truth class (rows sum to 100)", fontsize=9)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=120, bbox_inches="tight")


# ------------------------------------------------------------------------------------------------- main


def run(argv: list[str] | None = None) -> int:
    """Read and check every json (before anything is written), then write OUT.json, OUT.md and the confusion PNG."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=Path, required=True, help="folder of the WORLD_sSEED run folders")
    parser.add_argument("--worlds", nargs="+", default=list(DEFAULT_WORLDS), help="first = before, last = after")
    parser.add_argument("--seeds", nargs="+", type=int, help="default: every WORLD_sN folder found")
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help="output stem: OUT.json, OUT.md, OUT_confusion.png"
    )
    args = parser.parse_args(argv)
    worlds = [check_plain_name(world, "--worlds: the world") for world in args.worlds]
    if len(worlds) < 2 or len(set(worlds)) != len(worlds):
        raise InputError(f"--worlds {' '.join(worlds)}: expected at least two distinct worlds (before ... after)")
    if not args.runs.is_dir():
        raise InputError(f"{args.runs}: not a folder (expected the folder of the WORLD_sSEED runs)")
    seeds = sorted(set(args.seeds)) if args.seeds else find_seeds(args.runs, worlds)
    if not seeds:
        raise InputError(f"{args.runs}: no run folder {worlds[0]}_sN or {worlds[-1]}_sN (N = the seed)")
    loaded, missing = load_runs(args.runs, worlds, seeds)
    classes = check_same_classes(loaded, args.runs)
    table = build_table(loaded, missing, worlds, seeds, classes)
    command = shlex.join(["python", "benchmarks/reports/transfer_table.py", *(sys.argv[1:] if argv is None else argv)])
    out = args.out
    figure = f"{out.name}_confusion.png" if table["classes_present"] else None
    table = {"command": command, "runs": str(args.runs), **table, "figures": {"confusion": figure}}
    make_folder(out.parent)
    if figure:
        plot_confusions(table, out.parent / figure)
    json_path, md_path = out.parent / f"{out.name}.json", out.parent / f"{out.name}.md"
    atomic_write_json(json_path, table)
    markdown = to_markdown(table)
    atomic_write_text(md_path, markdown)
    print(markdown)
    print(f"-> {json_path}, {md_path}" + (f", {out.parent / figure}" if figure else ""))
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with bad input (a file, a flag) as a one-line error and exit code 2."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
