"""Paired TTCE / CTC differences between generated banks that share their conditioning trajectories.

    python benchmarks/reports/temporal_paired.py --bank u4d_most=runs/temporal/banks/u4d_most_s1 \
        --bank baseline_most=runs/temporal/banks/baseline_most_s1 \
        --bank u4d_no_temporal=runs/temporal/banks/u4d_no_temporal_s1 \
        --out benchmarks/results/temporal/temporal_paired_s1

Banks generated with the same seed draw the same ego trajectories (`poses.txt`), so each sequence is a matched pair
across methods and the per-sequence difference removes the trajectory's own difficulty (a sharp turn is hard for
every method). For every bank after the first (the reference) and every interval k: the mean over sequences of
(bank - reference), where a sequence's score is the mean of its pairs (i, i + k) as u4d_aug.metrics.temporal scores
them (the pooled mean of `u4d evaluate`, since every sequence has the same frames), a 95 % bootstrap interval
resampling sequences (pairs within a sequence share frames, so sequences are the independent unit), and the share
of sequences where the reference scores lower. The banks must hold the same sequences with the same poses.
`--metrics` picks among ttce, ttce_global (ICP started from a FPFH + RANSAC registration: `u4d evaluate --metrics
ttce_global`, ~8 s per generated pair) and ctc; default ttce,ctc.

Writes OUT.json and OUT.md:
    reference: NAME; banks: {NAME: path}; sequences: [ids]; boot: resamples; seed; metrics: [names]
    means.NAME.METRIC.K: the bank's mean (equal to `u4d evaluate`'s table2 for that bank)
    paired.NAME.METRIC.K: {mean_diff, ci_low, ci_high, reference_lower_share, n} for NAME - reference
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from u4d_aug.bank import named_banks, sequence_ids
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import atomic_write_json, atomic_write_text, make_folder
from u4d_aug.metrics import temporal
from u4d_aug.progress import progress_bar

METRICS = {"ttce": temporal.TTCE_INTERVALS, "ttce_global": temporal.TTCE_INTERVALS, "ctc": temporal.CTC_INTERVALS}
DEFAULT_METRICS = ("ttce", "ctc")
UNITS = {"ttce": "m", "ttce_global": "m", "ctc": "m^2"}


def sequence_scores(
    sequence_dir: Path, metrics: tuple[str, ...] = DEFAULT_METRICS
) -> tuple[np.ndarray, dict[str, dict[int, float]]]:
    """(poses (T, 4, 4), {metric: {k: mean over the sequence's pairs}}) of one SemanticKITTI-layout sequence."""
    scans, poses = temporal.load_kitti_sequence(sequence_dir)
    scores = {}
    for metric in metrics:
        if metric == "ttce":
            scores[metric] = temporal.ttce(scans, poses).mean
        elif metric == "ttce_global":
            scores[metric] = temporal.ttce(scans, poses, registration="global").mean
        elif metric == "ctc":
            scores[metric] = temporal.ctc(scans, poses).mean
        else:
            raise InputError(f"--metrics: unknown metric {metric!r}; expected some of {', '.join(METRICS)}")
    return poses, scores


def paired_difference(reference: np.ndarray, other: np.ndarray, boot: int, rng: np.random.Generator) -> dict:
    """Mean of other - reference over matched units (S,), its 95 % bootstrap interval and P(reference lower)."""
    diff = np.asarray(other, dtype=np.float64) - np.asarray(reference, dtype=np.float64)  # (S,)
    finite = np.isfinite(diff)
    diff = diff[finite]
    if diff.size == 0:
        return {"mean_diff": None, "ci_low": None, "ci_high": None, "reference_lower_share": None, "n": 0}
    means = diff[rng.integers(0, diff.size, size=(boot, diff.size))].mean(axis=1)  # (boot,)
    low, high = np.quantile(means, [0.025, 0.975])
    return {
        "mean_diff": float(diff.mean()),
        "ci_low": float(low),
        "ci_high": float(high),
        "reference_lower_share": float(np.mean(diff > 0)),
        "n": int(diff.size),
    }


def score_banks(
    banks: dict[str, Path], progress: bool = True, metrics: tuple[str, ...] = DEFAULT_METRICS
) -> tuple[list[str], dict]:
    """Sequence ids and {bank: {metric: {k: (S,) per-sequence scores}}}; raises unless every bank matches the first."""
    names = list(banks)
    first = banks[names[0]]
    ids = sequence_ids(first)
    per_bank: dict[str, dict] = {}
    reference_poses: dict[str, np.ndarray] = {}
    for name in names:
        root = banks[name]
        found = sequence_ids(root)
        if found != ids:
            raise InputError(f"{root / 'sequences'}: sequences {found} differ from {first / 'sequences'}'s {ids}")
        table = {m: {k: [] for k in METRICS[m]} for m in metrics}
        for seq in progress_bar(ids, desc=name, unit="sequence", enabled=progress, leave=False):
            poses, scores = sequence_scores(root / "sequences" / seq, metrics)
            if seq not in reference_poses:
                reference_poses[seq] = poses
            elif poses.shape != reference_poses[seq].shape or not np.allclose(poses, reference_poses[seq], atol=1e-6):
                raise InputError(
                    f"{root / 'sequences' / seq / 'poses.txt'}: poses differ from "
                    f"{first / 'sequences' / seq / 'poses.txt'}; paired scores need banks drawn with the same seed"
                )
            for metric in metrics:
                for k in METRICS[metric]:
                    table[metric][k].append(scores[metric][k])
        per_bank[name] = {m: {k: np.asarray(v) for k, v in t.items()} for m, t in table.items()}
    return ids, per_bank


def report(
    banks: dict[str, Path],
    boot: int = 10000,
    seed: int = 0,
    progress: bool = True,
    metrics: tuple[str, ...] = DEFAULT_METRICS,
) -> dict:
    """The OUT.json dictionary: bank means and paired differences against the first bank."""
    if len(banks) < 2:
        raise InputError("--bank: give at least two banks (the first is the reference)")
    ids, per_bank = score_banks(banks, progress, metrics)
    reference = next(iter(banks))
    rng = np.random.default_rng(seed)
    means = {
        name: {m: {str(k): float(np.nanmean(v)) for k, v in t.items()} for m, t in table.items()}
        for name, table in per_bank.items()
    }
    paired = {
        name: {
            m: {str(k): paired_difference(per_bank[reference][m][k], v, boot, rng) for k, v in t.items()}
            for m, t in table.items()
        }
        for name, table in per_bank.items()
        if name != reference
    }
    return {
        "reference": reference,
        "banks": {name: str(path) for name, path in banks.items()},
        "sequences": ids,
        "boot": boot,
        "seed": seed,
        "metrics": list(metrics),
        "units": {m: UNITS[m] for m in metrics},
        "means": means,
        "paired": paired,
    }


def _cell(entry: dict) -> str:
    if entry["mean_diff"] is None:
        return "-"
    return (
        f"{entry['mean_diff']:+.3f} [{entry['ci_low']:+.3f}, {entry['ci_high']:+.3f}] "
        f"({100 * entry['reference_lower_share']:.0f} %)"
    )


def markdown(result: dict, command: str) -> str:
    """OUT.md: the means and the paired differences against the reference."""
    ref = result["reference"]
    columns = [(m, k) for m in result["metrics"] for k in METRICS[m]]
    heads = {"ttce": "TTCE", "ttce_global": "TTCE-global", "ctc": "CTC"}
    header = "| | " + " | ".join(f"{heads[m]} k={k} ({UNITS[m]})" for m, k in columns) + " |"
    rule = "|---" * (len(columns) + 1) + "|"
    lines = [
        "# Paired temporal differences",
        "",
        f"{len(result['sequences'])} sequences drawn along the same trajectories in every bank; reference `{ref}`.",
        "",
        "## Means",
        "",
        header,
        rule,
    ]
    for name, table in result["means"].items():
        lines.append(f"| {name} | " + " | ".join(f"{table[m][str(k)]:.3f}" for m, k in columns) + " |")
    lines += [
        "",
        f"## Bank minus {ref}",
        "",
        f"Mean difference over sequences [95 % bootstrap interval over sequences, {result['boot']} resamples] "
        f"(share of sequences where {ref} is lower); a positive difference means {ref} is better.",
        "",
        header,
        rule,
    ]
    for name, table in result["paired"].items():
        lines.append(f"| {name} | " + " | ".join(_cell(table[m][str(k)]) for m, k in columns) + " |")
    lines += ["", "Banks: " + ", ".join(f"{n} `{p}`" for n, p in result["banks"].items()), "", f"    {command}", ""]
    return "\n".join(lines)


def run(argv: list[str] | None = None) -> int:
    """Score the banks, write OUT.json and OUT.md, print the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bank", action="append", default=[], help="NAME=DIR, the first is the reference")
    parser.add_argument("--boot", type=int, default=10000, help="bootstrap resamples of the sequences")
    parser.add_argument("--seed", type=int, default=0, help="seed of the bootstrap")
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.json and OUT.md")
    parser.add_argument("--metrics", default=",".join(DEFAULT_METRICS), help=f"some of {','.join(METRICS)}")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.boot < 100:
        raise InputError(f"--boot: expected at least 100 resamples, got {args.boot}")
    metrics = tuple(m.strip() for m in args.metrics.split(",") if m.strip())
    unknown = [m for m in metrics if m not in METRICS]
    if unknown or not metrics:
        raise InputError(f"--metrics {args.metrics!r}: expected a comma list of {', '.join(METRICS)}")
    banks = named_banks(args.bank)
    result = report(banks, args.boot, args.seed, progress=not args.no_progress, metrics=metrics)
    make_folder(args.out.parent)
    command = "python benchmarks/reports/temporal_paired.py " + " ".join(sys.argv[1:] if argv is None else argv)
    text = markdown(result, command)
    atomic_write_json(args.out.parent / f"{args.out.name}.json", result)
    atomic_write_text(args.out.parent / f"{args.out.name}.md", text)
    print(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with bad input (a bank, a NAME=DIR) as a one-line error and exit code 2."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
