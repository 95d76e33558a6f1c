"""Collect 30-minute `seg-train` runs of one recipe (one per seed) into a results json and a learning-curve PNG.

Reads from each RUN folder what training and evaluation left there: `log.jsonl` (steps, wall-clock, periodic val
mIoU), `config.yaml` (seed), `hosts.jsonl` (the machine), and the `u4d seg-eval --json` outputs saved beside them:
`eval_96.json` (required), every `eval_96_VARIANT.json` (other evaluation options of the same scans, e.g.
`eval_96_views4.json` with `--views 4`, `eval_96_trilinear.json` with `--readout trilinear`) and `eval_real.json`
(real SemanticKITTI), if present. Prints a table per seed and the mean +- std over seeds, per variant too.

    python benchmarks/reports/collect_seg_runs.py runs/lean_v025_lr02_s0 runs/lean_v025_lr02_s1 runs/lean_v025_lr02_s2 \
        --command "THE TRAINING COMMAND" \
        --out benchmarks/results/segmentation/seg_cpu_rich/lean_voxel025_lr02_seeds.json

Writes OUT and OUT with `_learning_curve.png` in place of `.json`. `--shared RUN` marks a run that did not have the
machine to itself (`alone_on_machine: false` in the json; its steps in the budget are not comparable).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import yaml

from segmentation.plots import plot_learning_curve
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import atomic_write_json, read_json_file, read_jsonl

EVAL_COMMAND = (
    "OMP_NUM_THREADS=1 torchrun --standalone --nproc_per_node 2 -m u4d_aug.cli seg-eval RUN/model.pt data/sim_seg "
    "--sequences 88-99 --json [--readout trilinear] [--views N] > RUN/eval_96[_trilinear][_viewsN].json"
)
REAL_EVAL_COMMAND = (
    "OMP_NUM_THREADS=2 u4d seg-eval RUN/model.pt ../shared/data/real/semantickitti --json "
    "--device cpu > RUN/eval_real.json"
)
REAL_KEYS = ("num_scans", "classes_present", "miou_present", "miou", "ece_per_scan", "ece_pooled", "iou")


def read_json(path: Path, needed: tuple[str, ...]) -> dict:
    """A json file that must hold `needed` keys, or an InputError naming the file and the missing key."""
    data = read_json_file(path, "a `u4d seg-eval --json` output")
    missing = [k for k in needed if k not in data]
    if missing:
        raise InputError(f"{path}: expected the keys {', '.join(missing)} (a `u4d seg-eval --json` output)")
    return data


def collect_run(run: Path) -> dict:
    """One run's steps, time, host, held-out and real-scan figures and its periodic curve."""
    log_path = run / "log.jsonl"
    if not log_path.is_file():
        raise InputError(f"{log_path}: not found (is {run} a seg-train output folder?)")
    log = [r for r in read_jsonl(log_path) if "time" in r and "step" in r]
    if not log:
        raise InputError(f"{log_path}: no record with 'step' and 'time'")
    config_path = run / "config.yaml"
    if not config_path.is_file():
        raise InputError(f"{config_path}: not found")
    seed = (yaml.safe_load(config_path.read_text()) or {}).get("seed")
    hosts = run / "hosts.jsonl"
    evaluation = read_json(run / "eval_96.json", ("miou", "ece_per_scan", "ece_pooled", "iou"))
    variants = {
        path.stem.removeprefix("eval_96_"): read_json(path, ("miou", "ece_per_scan", "iou"))
        for path in sorted(run.glob("eval_96_*.json"))
    }
    real = run / "eval_real.json"
    real = read_json(real, REAL_KEYS) if real.exists() else None
    steps, seconds = max(r["step"] for r in log), max(r["time"] for r in log)
    return {
        "run": str(run),
        "seed": seed,
        "host": read_jsonl(hosts)[0] if hosts.is_file() else None,
        "steps": steps,
        "train_seconds": seconds,
        "seconds_per_step": seconds / steps,
        "miou_96": evaluation["miou"],
        "ece_per_scan_96": evaluation["ece_per_scan"],
        "ece_pooled_96": evaluation["ece_pooled"],
        "iou_96": evaluation["iou"],
        **{f"miou_96_{name}": v["miou"] for name, v in variants.items()},
        **{f"ece_per_scan_96_{name}": v["ece_per_scan"] for name, v in variants.items()},
        "variants": sorted(variants),
        "iou_96_variants": {name: v["iou"] for name, v in variants.items()},
        "real_semantickitti": {k: real[k] for k in REAL_KEYS} if real else None,
        "curve": [
            {"step": r["step"], "minutes": r["time"] / 60, "val_miou_10_scans": r["val_miou"]}
            for r in log
            if "val_miou" in r
        ],
        "_log": log,
    }


def mean_std(values: list[float]) -> tuple[float, float | None]:
    """Mean and sample standard deviation (None for one value)."""
    return statistics.mean(values), statistics.stdev(values) if len(values) > 1 else None


def shared_variants(rows: list[dict]) -> list[str]:
    """The evaluation variants (eval_96_VARIANT.json) every run has."""
    return [name for name in rows[0]["variants"] if all(name in r["variants"] for r in rows)]


def summarize(rows: list[dict], command: str) -> dict:
    """The results json: commands, mean +- std over the runs, per-class mean IoU, and every run."""
    alone = all(r["alone_on_machine"] for r in rows)
    summary: dict = {"command": command, "eval_command": EVAL_COMMAND, "alone_on_machine": alone}
    summary["miou_96_mean"], summary["miou_96_std"] = mean_std([r["miou_96"] for r in rows])
    summary["iou_96_mean"] = {c: statistics.mean(r["iou_96"][c] for r in rows) for c in rows[0]["iou_96"]}
    for name in shared_variants(rows):
        summary[f"miou_96_{name}_mean"], summary[f"miou_96_{name}_std"] = mean_std([r[f"miou_96_{name}"] for r in rows])
        summary[f"iou_96_{name}_mean"] = {
            c: statistics.mean(r["iou_96_variants"][name][c] for r in rows) for c in rows[0]["iou_96"]
        }
    reals = [r["real_semantickitti"]["miou_present"] for r in rows if r["real_semantickitti"]]
    if reals:
        summary["real_miou_present_mean"] = statistics.mean(reals)
        summary["real_eval_command"] = REAL_EVAL_COMMAND
    summary["runs"] = [{k: v for k, v in r.items() if k != "_log"} for r in rows]
    return summary


def curve_records(rows: list[dict]) -> list[dict]:
    """Training loss and periodic val mIoU of every run against wall-clock minutes, one key per seed."""
    records = []
    for row in rows:
        for r in row["_log"]:
            record = {"minutes": r["time"] / 60}
            if "val_miou" in r:
                record[f"val_miou_seed{row['seed']}"] = r["val_miou"]
            if "loss" in r:
                record[f"loss_seed{row['seed']}"] = r["loss"]
            records.append(record)
    return sorted(records, key=lambda r: r["minutes"])


def run(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="seg-train output folders, one per seed")
    parser.add_argument("--command", required=True, help="the training command, recorded in the json (seed=S)")
    parser.add_argument("--out", type=Path, required=True, help="results json; the PNG goes beside it")
    parser.add_argument(
        "--shared",
        type=Path,
        action="append",
        default=[],
        help="a run (one of RUNS) that did not have the machine to itself; recorded as alone_on_machine: false",
    )
    args = parser.parse_args(argv)
    unknown = [str(path) for path in args.shared if path not in args.runs]
    if unknown:
        raise InputError(f"--shared {', '.join(unknown)}: not among the runs given")
    if args.out.suffix != ".json":
        raise InputError(f"--out {args.out}: expected a .json path")
    rows = [{**collect_run(path), "alone_on_machine": path not in args.shared} for path in args.runs]
    summary = summarize(rows, args.command)
    atomic_write_json(args.out, summary)
    png = args.out.with_name(args.out.stem + "_learning_curve.png")
    plot_learning_curve(curve_records(rows), png, x_key="minutes")

    def pct(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.2f}"

    names = shared_variants(rows)
    head = "".join(f" {name:>{max(len(name), 6)}}" for name in names)
    print(f"{'run':<36} {'seed':>4} {'steps':>5} {'s/step':>6} {'mIoU':>6} {'ECE':>5}{head} {'real':>6}")
    for r in rows:
        real = r["real_semantickitti"]["miou_present"] if r["real_semantickitti"] else None
        cells = "".join(f" {pct(r[f'miou_96_{name}']):>{max(len(name), 6)}}" for name in names)
        print(
            f"{r['run']:<36} {r['seed']!s:>4} {r['steps']:>5} {r['seconds_per_step']:>6.2f} {pct(r['miou_96']):>6} "
            f"{pct(r['ece_per_scan_96']):>5}{cells} {pct(real):>6}"
        )
    for name in [""] + names:
        key = f"miou_96_{name}_" if name else "miou_96_"
        spread = "" if summary[key + "std"] is None else f" +- {pct(summary[key + 'std'])}"
        label = f" ({name})" if name else ""
        print(f"mean mIoU{label} over {len(rows)} runs: {pct(summary[key + 'mean'])}{spread} %")
    print(f"-> {args.out}, {png}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with a missing or malformed run file as a one-line error."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
