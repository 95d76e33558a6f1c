"""The generator recipe pilots in one table: each pilot's budget, its one-call denoising error at the log-SNRs the
samplers end on, and its gates (teacher kept / building share, BEV points per cell, roughness, FRD, FPD).

    python benchmarks/reports/pilot_table.py --pilots ../runs/pilots --gates ../runs/pilots/gates_round1.json \
        --out benchmarks/results/generation/pilots.json

Reads PILOTS/NAME/denoise.json (`benchmarks/diagnostics/diag_denoise.py`), the gate rows of NAME from the --gates
files or PILOTS/NAME/gates.json (`benchmarks/gates.py`) and the training budget from each run folder's log (steps,
batch, step time); writes OUT (json) and OUT with .md. The reference rows (real, real projected) come from the first
gates file.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json, atomic_write_text

GATE_KEYS = ("teacher_kept_share", "teacher_building_share", "bev_points_per_cell", "ring_roughness", "frd", "fpd")
PROBE_LOG_SNRS = (2.0, 5.0, 8.0)  # the 20-step time grid's last call is at log-SNR 5.07


def read_json(path: Path) -> dict:
    """A json file, or InputError naming it."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not a readable json file ({exc})") from None


def run_budget(folder: Path) -> dict:
    """Steps, batch and median seconds per step of a train-diffusion run folder (its log and config)."""
    lines = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines() if line.strip()]
    if not lines:
        raise InputError(f"{folder}: empty log.jsonl")
    config = (folder / "config.yaml").read_text()
    batch = next((int(line.split(":")[1]) for line in config.splitlines() if line.startswith("batch_size:")), 0)
    seconds = sorted(line["sec_per_step"] for line in lines)
    return {"steps": lines[-1]["step"], "batch": batch, "sec_per_step": seconds[len(seconds) // 2]}


def pilot_row(folder: Path, gates: dict) -> dict:
    """One pilot: its runs' budgets, the denoising error per task and log-SNR, its gate row."""
    runs = [path.parent for path in sorted(folder.glob("*/log.jsonl"))]
    probe = read_json(folder / "denoise.json")
    errors = {}
    for task, net in probe["nets"].items():
        errors[task] = {f"{row['log_snr']:g}": row["error"] for row in net["rows"] if row["log_snr"] in PROBE_LOG_SNRS}
    return {
        "runs": {path.name: run_budget(path) for path in runs},
        "denoise_error": errors,
        "gates": {key: gates.get(key) for key in GATE_KEYS},
    }


def to_markdown(result: dict) -> str:
    """The pilot table: budget, stage-2 (or baseline) denoising error, gates; the reference rows first."""
    lines = [
        "# Generator recipe pilots (64x1024, one core each)",
        "",
        f"Built by `{result['command']}`. Budget: steps x batch per run (two nets: half each). Denoising error: one "
        "net call on 4 held-out scans noised to the log-SNR, mean |x̂0 − x0| of the depth on returns (encoded, "
        "[-1, 1]; the noise itself: 0.29 / 0.065 / 0.015); stage 2 = completion given the real P_u. Gates on 16 "
        "generated scans (`benchmarks/gates.py`).",
        "",
        "| pilot | budget | s/step | stage 2 error λ=2 / 5 / 8 | stage 1 error λ=5 | teacher kept % "
        "| building % of kept | points / BEV cell | ring roughness ×10³ | FRD | FPD |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in result["reference"].items():
        lines.append(f"| {name} | — | — | — | — | {_gate_cells(row)} |")
    for name, pilot in result["pilots"].items():
        budget = " + ".join(f"{r['steps']} x {r['batch']}" for r in pilot["runs"].values())
        seconds = " / ".join(f"{r['sec_per_step']:.2f}" for r in pilot["runs"].values())
        errors = pilot["denoise_error"]
        second = errors.get("stage2") or errors.get("baseline") or {}
        first = errors.get("stage1", {})
        probe = " / ".join(f"{second.get(f'{lam:g}', float('nan')):.4f}" for lam in PROBE_LOG_SNRS)
        lines.append(
            f"| {name} | {budget} | {seconds} | {probe} | {first.get('5', float('nan')):.4f} | "
            f"{_gate_cells(pilot['gates'])} |"
        )
    return "\n".join(lines) + "\n"


def _gate_cells(row: dict) -> str:
    def pct(key: str) -> str:
        return "—" if row.get(key) is None else f"{100 * row[key]:.1f}"

    def num(key: str, scale: float = 1.0, digits: int = 2) -> str:
        return "—" if row.get(key) is None else f"{scale * row[key]:,.{digits}f}"

    return " | ".join(
        [pct("teacher_kept_share"), pct("teacher_building_share"), num("bev_points_per_cell"),
         num("ring_roughness", 1000.0, 1), num("frd", digits=0), num("fpd", digits=0)]
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--pilots", type=Path, required=True, help="folder of pilot folders (scripts/generator_pilots.sh)"
    )
    parser.add_argument("--gates", type=Path, nargs="*", default=[], help="gates.py json files holding pilot rows")
    parser.add_argument("--out", type=Path, required=True, help="OUT.json (and OUT.md)")
    args = parser.parse_args(argv)
    try:
        files = [read_json(path) for path in args.gates]
        rows = {name: row for file in files for name, row in file["rows"].items()}
        pilots = {}
        for folder in sorted(p for p in args.pilots.iterdir() if (p / "denoise.json").is_file()):
            gate_file = folder / "gates.json"
            gates = read_json(gate_file)["rows"] if gate_file.is_file() else {}
            gates = gates.get(folder.name) or rows.get(folder.name) or {}
            pilots[folder.name] = pilot_row(folder, gates)
        if not pilots:
            raise InputError(f"{args.pilots}: no pilot folder with a denoise.json")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    reference = {name: rows[name] for name in ("reference", "real", "real projected") if name in rows}
    result = {"command": " ".join(["python", *sys.argv]), "reference": reference, "pilots": pilots}
    text = to_markdown(result)
    print(text)
    atomic_write_json(args.out, result)
    atomic_write_text(args.out.with_suffix(".md"), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
