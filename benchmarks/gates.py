"""Gate scores of generated banks on what matters downstream: the teacher's view, BEV density, roughness,
FRD / FPD, beside real scans and real scans made like generated ones.

    python benchmarks/gates.py --bank baseline=BANK_DIR [--bank u4d=DIR ...] --real data/sim_eval \\
        --real-sequences 00-11 --num 16 --out benchmarks/results/generation/gates.json

A bank is a SemanticKITTI-layout folder (`sequences/XX/velodyne/*.bin`, as `u4d generate` writes); its first `--num`
scans (sorted) are scored. The reference is `--num` real scans of `--real-sequences` drawn with `--seed`; the
"real" row is `--num` scans of `--floor-sequences` (default: the other sequences of ROOT) drawn alike, and "real
projected" the same scans after the trip a generated scan makes (project -> to_image -> unproject at the sensor's
H x W, beam rows): the row a generator at that resolution is compared with. Metrics (`--metrics`, the names of
`bench_generation.py`): teacher = the share of points `--teacher` keeps as pseudo-labels (softmax >= its
semi.pseudo_threshold, each scan cut and augmented as the mean teacher's unlabelled stream does) and the class mix of
those labels (building share the headline), bev_density = above-ground points per occupied 0.25 m BEV cell,
roughness = mean |encoded depth step| along a ring and down a column (`u4d_aug.metrics.structure`), frd / fpd =
`u4d evaluate` against the reference with the shipped extractors. The teacher, density and roughness describe a
row's own scans, so the reference row has them too; FRD / FPD of the reference against itself are not computed.
`--autoencoder` adds the real row's scans through a latent generator's autoencoder, `--detail` the real row's
layouts (their projection at W / s columns) completed by a cascade's detail net, `--layout-nearest S` those layouts
with each column repeated S times (`u4d generate detail=nearest`): the best each can do.
Writes OUT (json: `rows.<name>.<key>`, the keys of bench_generation's `methods`, plus `scans` and `seconds`) and
OUT with .md; prints the table. 16 scans per bank take ~1 min on one core (FPD's point net is most of it).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import torch
from bank_confidence import parse_banks
from bench_generation import (
    STRUCTURE,
    WEIGHTS,
    autoencoded_bank,
    detailed_bank,
    floor_bank,
    layout_nearest_bank,
    parse_bench_metrics,
    projected_bank,
    score_bank,
)

from segmentation.teacher_view import load_teacher
from u4d_aug.data.datasets import expand_sequences, list_sequences
from u4d_aug.data.sensors import get_sensor
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text, make_folder
from u4d_aug.metrics.evaluate import list_scans

DEFAULT_METRICS = "teacher,bev_density,roughness,frd,fpd"
COLUMNS = (  # (json key, markdown header, scale, digits)
    ("teacher_kept_share", "teacher kept %", 100.0, 1),
    ("teacher_building_share", "building % of kept", 100.0, 1),
    ("bev_points_per_cell", "points / BEV cell", 1.0, 2),
    ("ring_roughness", "ring roughness ×10³", 1e3, 2),
    ("vertical_roughness", "vertical roughness ×10³", 1e3, 2),
    ("frd", "FRD ↓", 1.0, 0),
    ("fpd", "FPD ↓", 1.0, 1),
)
REFERENCE, REAL, PROJECTED, AUTOENCODED = "reference", "real", "real projected", "real autoencoded"
DETAILED = "real layout detailed"
AE_FILE = "the OUT/autoencoder.pt of `u4d train-autoencoder`"
DETAIL_FILE = "the weights of a cascade's detail net (`u4d train-diffusion stage=detail`, `u4d export-weights`)"


def score_row(
    bank: Path, reference: Path, metrics: tuple[str, ...], args: argparse.Namespace, geometry: dict, teacher
) -> dict:
    """One row: `bench_generation.score_bank` of the first --num scans of `bank`, with their count and the seconds."""
    start = time.perf_counter()
    extractors = (args.extractor_frd, args.extractor_fpd)
    values = score_bank(bank, reference, None, metrics, extractors, geometry, teacher, max_scans=args.num)
    return values | {"scans": len(list_scans(bank, args.num)), "seconds": round(time.perf_counter() - start, 1)}


def parse_autoencoders(texts: list[str], option: str = "--autoencoder", what: str = AE_FILE) -> dict[str, Path]:
    """`option` NAME=FILE, repeatable (--autoencoder, --detail): {name: file}."""
    found = {}
    for text in texts:
        name, sep, file = text.partition("=")
        if not sep or not name or not Path(file).is_file():
            raise InputError(f"{option} {text!r}: expected NAME=FILE, FILE {what}")
        found[name] = Path(file)
    return found


def file_digest(path: Path) -> str:
    """The first 12 hex digits of the sha256 of a file."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]


def other_sequences(root: Path, taken: list[str]) -> list[str]:
    """The sequences of `root` not in `taken` (names or A-B ranges)."""
    taken_names = set(expand_sequences(taken))
    rest = [seq for seq in list_sequences(root) if seq not in taken_names]
    if not rest:
        raise InputError(f"{root}: no sequence left outside --real-sequences for the real row; give --floor-sequences")
    return rest


def gate_rows(
    args: argparse.Namespace, banks: dict[str, Path], metrics: tuple[str, ...], geometry: dict, teacher
) -> dict:
    """{row name: values}: the reference, real and real-projected rows, then each bank."""
    work = args.work
    reference = floor_bank(args.real, args.real_sequences, args.num, args.seed, work / f"reference_n{args.num}")
    real = floor_bank(args.real, args.floor_sequences, args.num, args.seed, work / f"real_n{args.num}")
    projected = projected_bank(real, geometry, work / f"real_projected_n{args.num}")
    encoded = {  # keyed by the file's digest: a retrained autoencoder never reuses another's scans
        f"{AUTOENCODED} ({name})": autoencoded_bank(
            real, path, geometry, work / f"real_ae_{file_digest(path)}_n{args.num}"
        )
        for name, path in getattr(args, "autoencoders", {}).items()
    }
    detailed = {  # likewise keyed by the detail net's digest
        f"{DETAILED} ({name})": detailed_bank(
            real, path, geometry, work / f"real_detail_{file_digest(path)}_n{args.num}"
        )
        for name, path in getattr(args, "details", {}).items()
    }
    nearest = {
        f"real layout nearest (1/{stride})": layout_nearest_bank(
            real, stride, geometry, work / f"real_nearest_{stride}_n{args.num}"
        )
        for stride in getattr(args, "layout_nearest", [])
    }
    own = tuple(m for m in metrics if m in STRUCTURE)  # the reference against itself: no FRD / FPD
    rows = {REFERENCE: score_row(reference, reference, own, args, geometry, teacher) if own else {}}
    for name, bank in {REAL: real, PROJECTED: projected, **encoded, **nearest, **detailed, **banks}.items():
        rows[name] = score_row(bank, reference, metrics, args, geometry, teacher)
        print(f"{name}: {summary_line(rows[name])}", flush=True)
    return rows


def summary_line(values: dict) -> str:
    """The row's scalar values in one line."""
    return ", ".join(f"{key} {values[key]:.4g}" for key, *_ in COLUMNS if values.get(key) is not None)


def _cell(value: float | None, scale: float, digits: int) -> str:
    return "—" if value is None else f"{value * scale:,.{digits}f}"


def to_markdown(result: dict) -> str:
    """The gate table (rows: reference, real, real projected, real autoencoded, banks) and each row's largest
    pseudo-label classes."""
    rows = result["rows"]
    keys = [c for c in COLUMNS if any(row.get(c[0]) is not None for row in rows.values())]
    lines = [
        "# Gates: what a segmentor reads in each bank",
        "",
        f"Generated by `{result['command']}` (do not edit by hand).",
        "",
        f"{result['num']} scans per row. Reference: real scans of sequences {' '.join(result['real_sequences'])} of "
        f"`{result['real']}`; real: of sequences {' '.join(result['floor_sequences'])}; real projected: the real "
        f"row's scans through the {result['geometry']['height']}x{result['geometry']['width']} range image. Teacher "
        f"`{result['teacher']}` (kept = softmax >= {result.get('pseudo_threshold')}); FRD / FPD against the "
        "reference.",
        "",
        "| row | " + " | ".join(header for _, header, *_ in keys) + " | s |",
        "|---" * (len(keys) + 2) + "|",
    ]
    for name, row in rows.items():
        cells = [_cell(row.get(key), scale, digits) for key, _, scale, digits in keys]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {row.get('seconds', '—')} |")
    mixes = {name: row["teacher_class_share"] for name, row in rows.items() if row.get("teacher_class_share")}
    if mixes:
        lines += ["", "The teacher's kept pseudo-labels, % per class (the six largest of the real row):", ""]
        classes = sorted(mixes.get(REAL, next(iter(mixes.values()))).items(), key=lambda kv: -kv[1])[:6]
        names = [name for name, _ in classes]
        lines += ["| row | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
        lines += [f"| {row} | " + " | ".join(f"{100 * mix[n]:.1f}" for n in names) + " |" for row, mix in mixes.items()]
    return "\n".join(lines) + "\n"


def add_scoring_arguments(parser: argparse.ArgumentParser, floor_help: str, sensor_help: str, work: str) -> None:
    """The arguments of a script that scores rows of scans against real ones as the gates do: --real,
    --real-sequences, --floor-sequences, --num, --teacher, --extractor-frd/-fpd, --sensor, --work, --out."""
    parser.add_argument("--real", type=Path, required=True, help="SemanticKITTI root of the real scans")
    parser.add_argument("--real-sequences", nargs="+", required=True, help="the reference's sequences (e.g. 00-11)")
    parser.add_argument("--floor-sequences", nargs="+", default=None, help=floor_help)
    parser.add_argument("--num", type=int, default=16, help="scans per row")
    parser.add_argument("--teacher", type=Path, default=WEIGHTS / "uncertainty_segmentor.pt")
    parser.add_argument("--extractor-frd", type=Path, default=WEIGHTS / "extractor_frd.pt")
    parser.add_argument("--extractor-fpd", type=Path, default=WEIGHTS / "extractor_fpd.pt")
    parser.add_argument("--sensor", default="hdl64", help=sensor_help)
    parser.add_argument("--work", type=Path, default=Path(work), help="the rows' bank folders go here")
    parser.add_argument("--out", type=Path, required=True, help="FILE.json (and FILE.md)")


def beam_geometry(sensor_name: str) -> dict:
    """{sensor, height, width, row_mode}: the sensor's own range image in beam rows, where roughness is measured."""
    sensor = get_sensor(sensor_name)
    return {"sensor": sensor_name, "height": sensor.height, "width": sensor.width, "row_mode": "beam"}


def run(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bank", action="append", default=[], metavar="NAME=DIR", help="a bank (repeatable)")
    parser.add_argument("--seed", type=int, default=0, help="draws the reference's and the real row's scans")
    parser.add_argument(
        "--autoencoder", action="append", default=[], metavar="NAME=FILE",
        help="a latent generator's autoencoder (OUT/autoencoder.pt): adds the row of the real scans through it",
    )  # fmt: skip
    parser.add_argument(
        "--detail", action="append", default=[], metavar="NAME=FILE",
        help="a cascade's detail net: adds the row of the real scans' layouts (W / s columns) completed by it",
    )  # fmt: skip
    parser.add_argument(
        "--layout-nearest", action="append", type=int, default=[], metavar="S",
        help="adds the row of the real scans' layouts at W / S columns, each column repeated S times (detail=nearest)",
    )  # fmt: skip
    parser.add_argument("--metrics", default=DEFAULT_METRICS, help=f"subset of {DEFAULT_METRICS} (bench_generation's)")
    add_scoring_arguments(parser, "the real row's sequences (default: the other ones)",
                          "the range image of the real-projected row and roughness", "runs/gates")  # fmt: skip
    args = parser.parse_args(argv)
    if args.num < 1:
        raise InputError(f"--num must be >= 1, got {args.num}")
    metrics = parse_bench_metrics(args.metrics)
    banks = parse_banks(args.bank)
    args.autoencoders = parse_autoencoders(args.autoencoder)
    args.details = parse_autoencoders(args.detail, "--detail", DETAIL_FILE)
    args.floor_sequences = args.floor_sequences or other_sequences(args.real, args.real_sequences)
    make_folder(args.out.parent)  # a file in the way: one line before the long computation
    torch.set_num_threads(1)
    geometry = beam_geometry(args.sensor)
    teacher = load_teacher(args.teacher) if "teacher" in metrics else None
    rows = gate_rows(args, banks, metrics, geometry, teacher)
    result = {
        "benchmark": "gates",
        "command": "python benchmarks/gates.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": host_info(),
        "real": str(args.real),
        "real_sequences": args.real_sequences,
        "floor_sequences": args.floor_sequences,
        "num": args.num,
        "seed": args.seed,
        "metrics": list(metrics),
        "teacher": str(args.teacher),
        "pseudo_threshold": teacher[0].semi.pseudo_threshold if teacher else None,
        "extractors": {"frd": str(args.extractor_frd), "fpd": str(args.extractor_fpd)},
        "geometry": geometry,
        "banks": {name: str(path) for name, path in banks.items()},
        "autoencoders": {name: str(path) for name, path in args.autoencoders.items()},
        "details": {name: str(path) for name, path in args.details.items()},
        "rows": rows,
    }
    text = to_markdown(result)
    print(text)
    atomic_write_json(args.out, result)
    atomic_write_text(args.out.with_suffix(".md"), text)
    return 0


def main(argv: list[str] | None = None) -> int:
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
