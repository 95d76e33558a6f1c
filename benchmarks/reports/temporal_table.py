"""The paper's Table 2 (TTCE, CTC) over seeds, and the MoST fusion ablation, from `u4d evaluate` evaluation.json files.

    python benchmarks/reports/temporal_table.py --method u4d_most=runs/eval/u4d_most_s0 \
        --method u4d_most=runs/eval/u4d_most_s1 --method floor=runs/eval/floor \
        --fusion gating=runs/eval/fusion_gating --out benchmarks/results/temporal/temporal

Each DIR holds the evaluation.json of `u4d evaluate --json --out DIR` (u4d_aug/metrics/evaluate.py); repeating a NAME
adds a seed. A method's score is its "table2.bank" side (for the real floor, the bank is the held-out real sequences)
and "table1.frd". Nothing is recomputed. The budget.json that scripts/temporal_queue.sh leaves beside an evaluation
(each trained net's steps, minutes, stage and batch: U4D as two nets stage1 + stage2, or with ONE_NET=1 one net u4d)
is listed with the sources. Writes OUT.json and OUT.md (two tables, mean ± std over seeds, ddof 1 as
segmentation.experiment.mean_std; a missing entry shows its reason, never a number) and OUT.png (TTCE and CTC against
the interval k, one line per method and fusion variant, bars = std over seeds; the floor dashed black; TTCE-global
in a third panel where computed).

OUT.json:
    units: {ttce, ttce_global, ctc, frd}; intervals: {ttce: [3, 4], ttce_global: [3, 4], ctc: [1, 2, 3, 4]}
    methods.NAME and fusion.VARIANT, each:
        sources: [evaluation.json paths, one per seed], seeds: their count
        ttce.K / ctc.K: {mean, std, n, per_seed} (per_seed aligned with sources, null where a seed lacks the number),
            or ttce / ctc: {missing: reason} when no seed has one; ttce_global (TTCE with ICP from a global
            registration, `u4d evaluate --metrics ttce_global`) likewise, absent when no source computed it
        frd: {mean, std, n, per_seed} or {missing: reason}; absent when no source's table1 has frd
        missing: {source: reason} for the seeds whose temporal metrics are missing (absent when none)
        nets: [per seed, aligned with sources: budget.json's {net: {steps, minutes[, stage, batch_size]}} or null];
            absent when no seed has a budget.json
    figure: the PNG's file name (beside OUT.json)
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from segmentation.experiment import mean_std
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import atomic_write_json, atomic_write_text, make_folder, read_json_file
from u4d_aug.viz import plt, save_figure

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "results" / "temporal" / "temporal"
# u4d_aug.metrics.temporal TTCE_/CTC_INTERVALS
INTERVALS = {"ttce": ("3", "4"), "ttce_global": ("3", "4"), "ctc": ("1", "2", "3", "4")}
HEADS = {"ttce": "TTCE", "ttce_global": "TTCE-global", "ctc": "CTC"}
UNITS = {
    "ttce": "m (ICP translation error against the conditioning poses)",
    "ttce_global": "m (the same, ICP started from a FPFH + RANSAC registration instead of the identity)",
    "ctc": "m^2 (chamfer of frames aligned with their poses)",
    "frd": "FRD (table1 of u4d evaluate)",
}
EXAMPLE = "u4d_most=runs/eval/u4d_most_s0"


# ------------------------------------------------------------------------------------------------- inputs


def parse_source(text: str, flag: str) -> tuple[str, Path]:
    """'NAME=DIR' -> (NAME, DIR/evaluation.json); DIR may name the json itself."""
    name, sep, folder = text.partition("=")
    if not sep or not name.strip() or not folder.strip():
        raise InputError(f"{flag} {text!r}: expected NAME=DIR (a folder with evaluation.json), e.g. {EXAMPLE}")
    path = Path(folder)
    return name.strip(), path if path.suffix == ".json" else path / "evaluation.json"


def _check_number(value: object, where: str) -> float | None:
    """A json number or null (a non-finite number becomes null); an InputError naming the field else."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: expected a number or null, got {value!r}")
    return float(value) if math.isfinite(value) else None


def read_evaluation(path: Path) -> dict:
    """An evaluation.json checked for table2.bank (its ttce/ctc numbers or a 'missing' reason); InputError else."""
    result = read_json_file(path, "the evaluation.json of `u4d evaluate --json --out DIR`")
    if not isinstance(result, dict) or not isinstance(result.get("table2"), dict):
        raise InputError(f"{path}: no 'table2' object (run `u4d evaluate` with --metrics ttce,ctc)")
    bank = result["table2"].get("bank")
    if not isinstance(bank, dict):
        raise InputError(f"{path}: table2.bank: expected an object with ttce/ctc or 'missing'")
    if "missing" not in bank:
        for metric, ks in INTERVALS.items():
            scores = bank.get(metric, {})
            if not isinstance(scores, dict):
                raise InputError(f"{path}: table2.bank.{metric}: expected an object {{interval: value}}")
            for k in ks:
                _check_number(scores.get(k), f"{path}: table2.bank.{metric}.{k}")
    if not isinstance(result.get("table1", {}), dict):
        raise InputError(f"{path}: table1: expected an object {{metric: {{value: ...}}}}")
    frd = result.get("table1", {}).get("frd")
    if frd is not None and (not isinstance(frd, dict) or "value" not in frd):
        raise InputError(f"{path}: table1.frd: expected an object with 'value'")
    if frd is not None:
        _check_number(frd["value"], f"{path}: table1.frd.value")
    return result


def read_budget(evaluation: Path) -> dict | None:
    """The nets of the budget.json beside an evaluation.json (scripts/temporal_queue.sh), None without one."""
    path = evaluation.parent / "budget.json"
    if not path.is_file():
        return None
    record = read_json_file(path, "the budget.json of scripts/temporal_queue.sh")
    nets = record.get("nets") if isinstance(record, dict) else None
    if not isinstance(nets, dict) or not all(isinstance(net, dict) and "steps" in net for net in nets.values()):
        raise InputError(f"{path}: expected {{'nets': {{NAME: {{'steps': ..., 'minutes': ...}}}}}}")
    return nets


# ------------------------------------------------------------------------------------------------- numbers


def _stat(per_seed: list[float | None]) -> dict:
    """mean_std over the seeds plus the per-seed values (segmentation.experiment.mean_std, ddof 1)."""
    return {**mean_std(per_seed), "per_seed": per_seed}


def temporal_reason(bank: dict, metric: str) -> str | None:
    """Why a seed's table2.bank has no `metric` numbers, or None when it has some."""
    if "missing" in bank:
        return str(bank["missing"])
    if metric not in bank:
        return f"{metric} not computed (not in --metrics)"
    if all(bank[metric].get(k) is None for k in INTERVALS[metric]):
        return f"{metric} is null for every interval"
    return None


def summarize(sources: list[tuple[Path, dict]]) -> dict:
    """One method's (or fusion variant's) entry of OUT.json from its seeds' evaluation.json files."""
    entry: dict = {"sources": [str(path) for path, _ in sources], "seeds": len(sources)}
    banks = [result["table2"]["bank"] for _, result in sources]
    for metric, ks in INTERVALS.items():
        if metric == "ttce_global" and not any(metric in bank for bank in banks):
            continue  # an optional column: absent unless some seed computed it
        reasons = [temporal_reason(bank, metric) for bank in banks]
        if all(r is not None for r in reasons):
            entry[metric] = {"missing": "; ".join(dict.fromkeys(reasons))}
            continue
        entry[metric] = {
            k: _stat([None if r else _check_number(b[metric].get(k), "") for b, r in zip(banks, reasons)]) for k in ks
        }
    frds = [result.get("table1", {}).get("frd") for _, result in sources]
    if any(f is not None for f in frds):
        values = [None if f is None else _check_number(f["value"], "") for f in frds]
        if all(v is None for v in values):
            reasons = [(f or {}).get("missing") or "frd not computed" for f in frds]
            entry["frd"] = {"missing": "; ".join(dict.fromkeys(reasons))}
        else:
            entry["frd"] = _stat(values)
    missing = {str(path): str(bank["missing"]) for (path, _), bank in zip(sources, banks) if "missing" in bank}
    if missing:
        entry["missing"] = missing
    nets = [read_budget(path) for path, _ in sources]
    if any(n is not None for n in nets):
        entry["nets"] = nets
    return entry


def build_table(args_sources: list[tuple[str, Path]], loaded: dict[Path, dict]) -> dict:
    """{NAME: summarize(its seeds)} in the order the names first appear."""
    grouped: dict[str, list[tuple[Path, dict]]] = {}
    for name, path in args_sources:
        grouped.setdefault(name, []).append((path, loaded[path]))
    return {name: summarize(sources) for name, sources in grouped.items()}


# ------------------------------------------------------------------------------------------------- markdown


def _fmt(stat: dict) -> str:
    """'mean ± std' (4 significant digits) or '—' when there is no number."""
    if stat.get("mean") is None:
        return "—"
    return f"{stat['mean']:.4g} ± {stat['std']:.2g}"


def markdown_table(entries: dict, label: str) -> list[str]:
    """One markdown table (rows = entries, columns = TTCE/CTC per k and FRD) and the reasons of its missing cells."""
    with_frd = any("frd" in e for e in entries.values())
    metrics = [m for m in INTERVALS if m != "ttce_global" or any(m in e for e in entries.values())]
    cols = [f"{HEADS[m]} k={k} ({'m²' if m == 'ctc' else 'm'}) ↓" for m in metrics for k in INTERVALS[m]]
    cols += ["FRD ↓"] if with_frd else []
    lines = [f"| {label} | seeds | " + " | ".join(cols) + " |", "|---" * (len(cols) + 2) + "|"]
    notes = []
    for name, entry in entries.items():
        cells = []
        for metric in metrics:
            if metric not in entry:
                cells += ["missing"] * len(INTERVALS[metric])
                notes.append(f"- {name}: {HEADS[metric]} missing: not computed")
            elif "missing" in entry[metric]:
                cells += ["missing"] * len(INTERVALS[metric])
                notes.append(f"- {name}: {metric.upper()} missing: {entry[metric]['missing']}")
            else:
                cells += [_fmt(entry[metric][k]) for k in INTERVALS[metric]]
        if with_frd:
            frd = entry.get("frd", {"missing": "frd not computed"})
            cells.append("missing" if "missing" in frd else _fmt(frd))
            if "missing" in frd:
                notes.append(f"- {name}: FRD missing: {frd['missing']}")
        for source, reason in entry.get("missing", {}).items():
            if all("missing" not in entry.get(m, {}) for m in metrics):  # only some seeds lack numbers
                notes.append(f"- {name}: seed `{source}` has no temporal metrics: {reason}")
        seeds = str(entry["seeds"]) + (" (< 2)" if entry["seeds"] < 2 else "")
        if label == "method" and name == "floor":
            seeds = f"{entry['seeds']} (real data)"  # the held-out sequences themselves: nothing to reseed
        lines.append(f"| {name} | {seeds} | " + " | ".join(cells) + " |")
    return lines + ([""] + notes if notes else [])


def to_markdown(table: dict) -> str:
    """OUT.md: Table 2 (methods) and the MoST fusion ablation, mean ± std over seeds, then the sources."""
    lines = [
        "# Temporal consistency (Table 2) and MoST fusion ablation",
        "",
        "Mean ± std over seeds (sample std, ddof 1; 0 for one seed). TTCE in metres: ICP translation error of "
        "frames k apart against the conditioning (ground-truth) poses, ICP from the identity (LC); TTCE-global: "
        "the same with ICP started from a FPFH + RANSAC registration (not LC), where a column is shown. "
        "CTC in m²: chamfer distance (squared "
        "nearest-neighbour) of frames k apart aligned with those poses. Lower is better. "
        "`floor` = held-out real sequences scored like a generator.",
        "",
        "## Table 2: temporal consistency",
        "",
    ]
    lines += markdown_table(table["methods"], "method") if table["methods"] else ["No --method given."]
    lines += ["", "## MoST fusion ablation", ""]
    lines += markdown_table(table["fusion"], "fusion") if table["fusion"] else ["No --fusion given."]
    lines += ["", f"![TTCE and CTC against k]({table['figure']})", "", "## Sources", ""]
    for part in ("methods", "fusion"):
        for name, entry in table[part].items():
            seeds = f"{entry['seeds']} seed" + ("s" if entry["seeds"] != 1 else "")
            line = f"- {part}/{name} ({seeds}): " + ", ".join(f"`{s}`" for s in entry["sources"])
            if "nets" in entry:
                line += "; trained: " + "; ".join(_nets_text(nets) for nets in entry["nets"])
            lines.append(line)
    return "\n".join(lines) + "\n"


def _nets_text(nets: dict | None) -> str:
    """One seed's nets as 'stage1 2000 steps x batch 1 (40.5 min) + stage2 ...', or '—' without a budget.json."""
    if nets is None:
        return "—"
    parts = []
    for name, net in nets.items():
        text = f"{name} {net['steps']} steps" + (f" x batch {net['batch_size']}" if "batch_size" in net else "")
        parts.append(text + (f" ({net['minutes']} min)" if net.get("minutes") is not None else ""))
    return " + ".join(parts)


# ------------------------------------------------------------------------------------------------- figure


def plot_intervals(table: dict, path: Path) -> Path:
    """OUT.png: TTCE, TTCE-global (where computed) and CTC mean against k per method (solid) and fusion variant
    (dotted), ± std."""
    entries = [entry for part in ("methods", "fusion") for entry in table[part].values()]
    metrics = [m for m in INTERVALS if m != "ttce_global" or any(m in entry for entry in entries)]
    fig, axes = plt.subplots(1, len(metrics), figsize=(5 * len(metrics), 3.8))
    for ax, metric in zip(axes, metrics):
        for part, style in (("methods", "-"), ("fusion", ":")):
            for name, entry in table[part].items():
                if metric not in entry or "missing" in entry[metric]:
                    continue
                stats = [(int(k), entry[metric][k]) for k in INTERVALS[metric]]
                points = [(k, s["mean"], s["std"]) for k, s in stats if s.get("mean") is not None]
                if not points:
                    continue
                x, mean, std = zip(*points)
                floor = part == "methods" and name == "floor"
                label = name if part == "methods" else f"fusion: {name}"
                ax.errorbar(
                    x, mean, yerr=std, capsize=3, marker="o", markersize=4, label=label,
                    linestyle="--" if floor else style, color="black" if floor else None,
                )  # fmt: skip
        ax.set_xticks([int(k) for k in INTERVALS[metric]])
        ax.set_xlabel("interval k (frames apart)")
        ax.set_ylabel(f"{HEADS[metric]} (m²)" if metric == "ctc" else f"{HEADS[metric]} (m)")
        ax.set_title(f"{HEADS[metric]} ↓, mean ± std over seeds", fontsize=10)
        ax.grid(alpha=0.3)
    legend = {label: handle for ax in axes for handle, label in zip(*ax.get_legend_handles_labels())}
    if legend:  # every line once, also one that has only CTC or only TTCE
        fig.legend(legend.values(), legend.keys(), loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


# ------------------------------------------------------------------------------------------------- main


def run(argv: list[str] | None = None) -> int:
    """Read and check every evaluation.json (before anything is written), then write OUT.png, OUT.json and OUT.md."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--method", action="append", default=[], metavar="NAME=DIR", help="a seed of a method")
    parser.add_argument("--fusion", action="append", default=[], metavar="VARIANT=DIR", help="a seed of a variant")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output stem: OUT.json, .md, .png")
    args = parser.parse_args(argv)
    if not args.method and not args.fusion:
        raise InputError(f"nothing to tabulate: give --method NAME=DIR (e.g. {EXAMPLE}) and/or --fusion VARIANT=DIR")
    methods = [parse_source(text, "--method") for text in args.method]
    fusion = [parse_source(text, "--fusion") for text in args.fusion]
    for flag, sources in (("--method", methods), ("--fusion", fusion)):
        seen = set()
        for name, path in sources:
            if (name, path) in seen:
                raise InputError(f"{flag} {name}: {path} given twice (a seed would count twice)")
            seen.add((name, path))
    loaded = {path: read_evaluation(path) for _, path in methods + fusion}
    table = {
        "units": UNITS,
        "intervals": {metric: [int(k) for k in ks] for metric, ks in INTERVALS.items()},
        "methods": build_table(methods, loaded),
        "fusion": build_table(fusion, loaded),
    }
    make_folder(args.out.parent)
    json_path, md_path = args.out.parent / f"{args.out.name}.json", args.out.parent / f"{args.out.name}.md"
    png_path = args.out.parent / f"{args.out.name}.png"
    table["figure"] = png_path.name
    plot_intervals(table, png_path)
    atomic_write_json(json_path, table)
    atomic_write_text(md_path, to_markdown(table))
    print(f"-> {json_path}, {md_path}, {png_path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with bad input (a file, a NAME=DIR) as a one-line error and exit code 2."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
