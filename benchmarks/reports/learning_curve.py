"""The generators' learning curves: FPD, FRD and the teacher's building share of each milestone bank against the
training step, for U4D and the baseline side by side, beside the real rows.

    python benchmarks/reports/learning_curve.py --final ../runs/final \
        --out benchmarks/results/generation/learning_curve.json

Reads FINAL/METHOD_milestones/gates_STEP.json (written by `scripts/generator_final.sh`: `benchmarks/gates.py` on the
16-scan bank of the net exported at STEP, row METHOD_STEP) for METHOD in --methods; writes OUT (json), OUT with .md and
OUT with .png (one panel per key; the real and real-projected rows as dashed lines).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json, atomic_write_text

KEYS = ("fpd", "frd", "teacher_building_share", "teacher_kept_share", "bev_points_per_cell", "ring_roughness")
PLOTTED = (("fpd", "FPD ↓", True), ("teacher_building_share", "teacher building share of kept points ↑", False))
REFERENCE_ROWS = ("real", "real projected")


def read_gates(path: Path) -> dict:
    """One gates.py json, or InputError naming it."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not a readable json file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("rows"), dict):
        raise InputError(f"{path}: expected a gates.py json with a 'rows' object")
    return data


def method_curve(folder: Path, method: str, prefix: str = "") -> tuple[dict, dict]:
    """({step: {key: value}}, the reference rows of the last file) of one method's milestone folder; `prefix`
    ("cascade_"): its PREFIXgates_STEP.json, rows PREFIXMETHOD_STEP."""
    curve, reference = {}, {}
    files = sorted(folder.glob(f"{prefix}gates_*.json"), key=lambda p: int(re.sub(r"\D", "", p.stem) or 0))
    for path in files:
        match = re.fullmatch(rf"{re.escape(prefix)}gates_(\d+)", path.stem)
        if match is None:  # another prefix's file (cascade_gates_N beside gates_N)
            continue
        step = int(match.group(1))
        rows = read_gates(path)["rows"]
        row = rows.get(f"{prefix}{method}_{step}")
        if row is None:
            raise InputError(f"{path}: no row '{prefix}{method}_{step}'")
        curve[step] = {key: row.get(key) for key in KEYS}
        reference = {name: {key: rows[name].get(key) for key in KEYS} for name in REFERENCE_ROWS if name in rows}
    return curve, reference


def to_markdown(result: dict) -> str:
    """One row per method and milestone step."""
    lines = [
        "# Generator learning curves (16 scans per milestone, scored at 64x1024)",
        "",
        f"Built by `{result['command']}`. Each milestone: the EMA net exported at that step, 16 scans (both stages 20 "
        "steps of DPM-Solver++(2M) SDE, the mean start), scored by `benchmarks/gates.py` against held-out places.",
        "",
        "| method | step | FPD | FRD | building % of kept | kept % | points / BEV cell | ring roughness ×10³ |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, row in result["reference"].items():
        lines.append(f"| {name} | — | {_cells(row)} |")
    for method, curve in result["methods"].items():
        for step, row in curve.items():
            lines.append(f"| {method} | {step} | {_cells(row)} |")
    return "\n".join(lines) + "\n"


def _cells(row: dict) -> str:
    def fmt(key: str, scale: float, digits: int) -> str:
        return "—" if row.get(key) is None else f"{scale * row[key]:,.{digits}f}"

    return " | ".join(
        [fmt("fpd", 1, 0), fmt("frd", 1, 0), fmt("teacher_building_share", 100, 1), fmt("teacher_kept_share", 100, 1),
         fmt("bev_points_per_cell", 1, 2), fmt("ring_roughness", 1000, 1)]
    )  # fmt: skip


def plot(result: dict, path: Path) -> None:
    """FPD (log scale) and building share against the step, one line per method, the real rows dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(PLOTTED), figsize=(5.5 * len(PLOTTED), 4))
    for axis, (key, label, log) in zip(axes, PLOTTED, strict=True):
        for method, curve in result["methods"].items():
            steps = sorted(step for step, row in curve.items() if row.get(key) is not None)
            axis.plot(steps, [curve[step][key] for step in steps], "o-", label=method)
        for name, row in result["reference"].items():
            if row.get(key) is not None:
                axis.axhline(row[key], linestyle="--", color="grey" if name == "real" else "black", label=name)
        axis.set_xlabel("training step")
        axis.set_ylabel(label)
        if log:
            axis.set_yscale("log")
        axis.legend(fontsize=8)
    figure.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    figure.savefig(tmp, dpi=110)
    plt.close(figure)
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--final", type=Path, required=True, help="folder of METHOD_milestones/ (generator_final.sh)")
    parser.add_argument("--methods", nargs="+", default=["u4d", "baseline"], help="the methods to draw")
    parser.add_argument(
        "--prefix", default="", help="cascade_: the milestones' cascade banks (generator_final.sh DETAIL=...)"
    )
    parser.add_argument("--out", type=Path, required=True, help="OUT.json (and OUT.md, OUT.png)")
    args = parser.parse_args(argv)
    methods, reference = {}, {}
    try:
        for method in args.methods:
            curve, ref = method_curve(args.final / f"{method}_milestones", method, args.prefix)
            if curve:
                methods[method] = curve
                reference = reference or ref
        if not methods:
            raise InputError(
                f"{args.final}: no METHOD_milestones/{args.prefix}gates_STEP.json for {' '.join(args.methods)}"
            )
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = {"command": " ".join(["python", *sys.argv]), "reference": reference, "methods": methods}
    text = to_markdown(result)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out, result)
    atomic_write_text(args.out.with_suffix(".md"), text)
    plot(result, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
