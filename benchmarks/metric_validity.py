"""Does each generation metric see a bad scan? FRD, FPD, JSD, MMD and the gates (teacher, BEV density, roughness) on
real held-out scans under controlled corruptions.

    python benchmarks/metric_validity.py --real data/sim_eval --real-sequences 00-11 --num 16 \\
        --work runs/metric_validity --out benchmarks/results/generation/metric_validity.json

The reference is `--num` real scans of `--real-sequences` drawn with `--seed` (as in gates.py); level 0 is `--num`
real scans of `--floor-sequences` (default: the other sequences of ROOT) drawn with `--seed`. Each `--kinds` corruption
of `u4d_aug.metrics.corruptions` (depth noise along the rays, smeared walls, dropped rows, swapped columns) is applied
to those scans at each `--levels` value (0 is always scored; scan i of kind k uses the generator seeded with
[seed, k, i] at every level, so the corruptions nest over the levels), written as a bank (SemanticKITTI layout) under
WORK and scored by `bench_generation.score_bank` against the reference (`--metrics`, the names of bench_generation).
SIGN holds the direction a metric must move when the scans get worse: the distances and the roughness rise, the
teacher's kept share, its building share and the points per BEV cell fall (away from a real scan's value).
The level-0 noise of a metric is how far it moves without any corruption: the largest |value(draw d) - value(level 0)|
over `--noise-draws` other draws of `--num` floor scans (seeds seed + 1, ...). Per kind and metric the json has
`rise` = sign * (value at the highest level - value at level 0), `monotone` (every step between neighbouring levels
moves in the sign's direction), and the verdict: "sees" when rise > noise, "wrong way" when -rise > noise, "cannot
see" otherwise. Writes OUT (json) and OUT with .md (the values, kinds x levels, and which metric sees which
corruption), prints the table. The banks under WORK are reused when present (delete them after changing a corruption).
The defaults score 15 banks of 16 scans (~1 min each on one core, FPD's point net and the teacher most of it).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_generation import HEADER, STRUCTURE, columns, floor_bank, parse_bench_metrics, score_bank
from gates import add_scoring_arguments, beam_geometry, other_sequences

from segmentation.teacher_view import load_teacher
from u4d_aug.data.formats import read_kitti_scan, write_kitti_scan
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text, make_folder
from u4d_aug.metrics.corruptions import CORRUPTIONS, corrupt
from u4d_aug.metrics.evaluate import list_scans

DEFAULT_METRICS = "frd,fpd,jsd,mmd,teacher,bev_density,roughness"
DEFAULT_LEVELS = (0.0, 0.25, 0.5, 1.0)
# the direction each metric must move as the scans get worse: +1 rises, -1 falls (away from a real scan's value)
SIGN = {
    "frd": 1,
    "fpd": 1,
    "jsd": 1,
    "mmd": 1,
    "rangejs": 1,
    "intensityjs": 1,
    "teacher_kept_share": -1,
    "teacher_building_share": -1,
    "bev_points_per_cell": -1,
    "ring_roughness": 1,
    "vertical_roughness": 1,
}


def parse_kinds(kinds: list[str]) -> tuple[str, ...]:
    """--kinds names -> a tuple of CORRUPTIONS in the order given; one line naming the accepted ones otherwise."""
    wrong = [kind for kind in kinds if kind not in CORRUPTIONS]
    if wrong or not kinds:
        raise InputError(f"--kinds {' '.join(wrong)}: expected some of {', '.join(CORRUPTIONS)}")
    return tuple(dict.fromkeys(kinds))


def parse_levels(levels: list[float]) -> tuple[float, ...]:
    """--levels -> sorted distinct levels with 0 added; each in [0, 1] and at least one above 0."""
    wrong = [level for level in levels if not 0.0 <= level <= 1.0]
    if wrong:
        raise InputError(f"--levels {' '.join(map(str, wrong))}: each level must be in [0, 1]")
    chosen = tuple(sorted({0.0, *levels}))
    if len(chosen) < 2:
        raise InputError("--levels: give at least one level above 0")
    return chosen


def checked_metrics(text: str) -> tuple[str, ...]:
    """`parse_bench_metrics` of --metrics, limited to the metrics with a direction in SIGN."""
    metrics = parse_bench_metrics(text)
    unsigned = [m for m in metrics if any(key not in SIGN for key in columns([m]))]
    if unsigned:
        raise InputError(f"--metrics {text!r}: {', '.join(unsigned)} has no direction; use some of {DEFAULT_METRICS}")
    return metrics


def level_tag(level: float) -> str:
    """0.25 -> '0.25': a level as a json key and in a folder name."""
    return f"{level:g}"


def corrupted_bank(clean: Path, kind: str, level: float, seed: int, sensor: str, out: Path) -> Path:
    """The scans of `clean` under `corrupt(kind, level)`, scan i with the generator seeded [seed, kind index, i]."""
    for i, (_, _, path) in enumerate(list_scans(clean)):
        target = out / "sequences" / "00" / "velodyne" / f"{i:06d}.bin"
        if not target.exists():
            rng = np.random.default_rng([seed, CORRUPTIONS.index(kind), i])
            write_kitti_scan(target, corrupt(read_kitti_scan(path), kind, level, rng, sensor))
    return out


def score(bank: Path, reference: Path, metrics: tuple[str, ...], args: argparse.Namespace, teacher) -> dict:
    """`bench_generation.score_bank` of the first --num scans of `bank`, with the seconds it took."""
    start = time.perf_counter()
    extractors = (args.extractor_frd, args.extractor_fpd)
    values = score_bank(bank, reference, None, metrics, extractors, args.geometry, teacher, max_scans=args.num)
    return values | {"seconds": round(time.perf_counter() - start, 1)}


def check(values: list[float | None], noise: float | None, sign: int) -> dict:
    """One kind and metric: rise (highest level over level 0, in the sign's direction), the level-0 noise,
    monotone (every step rises) and the verdict ("sees" / "wrong way" / "cannot see"; None without values)."""
    if any(v is None or not np.isfinite(v) for v in values) or noise is None or not np.isfinite(noise):
        return {"rise": None, "noise": noise, "monotone": None, "verdict": None}
    signed = [sign * v for v in values]
    rise = signed[-1] - signed[0]
    verdict = "sees" if rise > noise else "wrong way" if -rise > noise else "cannot see"
    monotone = all(b > a for a, b in zip(signed[:-1], signed[1:]))
    return {"rise": rise, "noise": noise, "monotone": monotone, "verdict": verdict}


def level_noise(clean: dict, draws: list[dict], keys: list[str]) -> dict[str, float | None]:
    """{key: the largest |value(draw) - value(level 0)|} over the other draws of uncorrupted scans."""
    noise = {}
    for key in keys:
        values = [draw.get(key) for draw in draws] + [clean.get(key)]
        if any(v is None or not np.isfinite(v) for v in values):
            noise[key] = None
        else:
            noise[key] = max(abs(v - clean[key]) for v in values[:-1])
    return noise


def validity_rows(args: argparse.Namespace, metrics: tuple[str, ...], teacher) -> dict:
    """Reference, level 0, the other draws and every kind x level: {"reference", "clean", "draws", "kinds"}."""
    work, num, seed = args.work, args.num, args.seed
    reference = floor_bank(args.real, args.real_sequences, num, seed, work / f"reference_n{num}_s{seed}")
    clean = floor_bank(args.real, args.floor_sequences, num, seed, work / f"clean_n{num}_s{seed}")
    own = tuple(m for m in metrics if m in STRUCTURE)  # the reference against itself: no distances
    rows: dict = {"reference": score(reference, reference, own, args, teacher) if own else {}}
    rows["clean"] = score(clean, reference, metrics, args, teacher)
    print(f"level 0: {rows['clean']}", flush=True)
    rows["draws"] = []
    for draw in range(1, args.noise_draws + 1):
        bank = floor_bank(args.real, args.floor_sequences, num, seed + draw, work / f"clean_n{num}_s{seed + draw}")
        rows["draws"].append(score(bank, reference, metrics, args, teacher))
        print(f"draw {draw}: {rows['draws'][-1]}", flush=True)
    rows["kinds"] = {}
    for kind in args.kinds:
        rows["kinds"][kind] = {level_tag(0.0): rows["clean"]}
        for level in args.levels[1:]:
            out = work / f"{kind}_{level_tag(level)}_n{num}_s{seed}"
            bank = corrupted_bank(clean, kind, level, seed, args.sensor, out)
            rows["kinds"][kind][level_tag(level)] = score(bank, reference, metrics, args, teacher)
            print(f"{kind} {level_tag(level)}: {rows['kinds'][kind][level_tag(level)]}", flush=True)
    return rows


def checks_of(rows: dict, keys: list[str]) -> tuple[dict, dict]:
    """The level-0 noise per key and {kind: {key: `check`}}."""
    noise = level_noise(rows["clean"], rows["draws"], keys)
    checks = {
        kind: {key: check([row.get(key) for row in levels.values()], noise[key], SIGN[key]) for key in keys}
        for kind, levels in rows["kinds"].items()
    }
    return noise, checks


def _cell(value: float | None) -> str:
    return "—" if value is None or not np.isfinite(value) else f"{value:.4g}"


def _verdict_cell(check: dict) -> str:
    if check["verdict"] is None:
        return "—"
    if check["verdict"] == "sees":
        return "sees" if check["monotone"] else "sees (not monotone)"
    return f"**{check['verdict']}**"


def to_markdown(result: dict) -> str:
    """The values (rows: reference, level 0, the other draws, the noise, then kinds x levels) and the verdicts."""
    keys, rows = result["keys"], result["rows"]
    headers = [HEADER[key].removesuffix(" ↓") + (" ↑" if SIGN[key] > 0 else " ↓") for key in keys]
    lines = [
        "# Metric validity: each metric on real scans under controlled corruptions",
        "",
        f"Generated by `{result['command']}` (do not edit by hand).",
        "",
        f"{result['num']} scans per row. Reference: real scans of sequences {' '.join(result['real_sequences'])} of "
        f"`{result['real']}`; level 0: real scans of sequences {' '.join(result['floor_sequences'])}, corrupted by "
        "`u4d_aug.metrics.corruptions` at each level. ↑ / ↓: the direction a metric must move as the scans get worse. "
        f"Noise: the largest change of a metric over {result['noise_draws']} other draws of uncorrupted scans.",
        "",
        "| kind | level | " + " | ".join(headers) + " |",
        "|---|---" + "|---" * len(keys) + "|",
    ]
    fixed = [("reference", "—", rows["reference"]), ("real", "0", rows["clean"])]
    fixed += [(f"real, draw {i + 1}", "0", row) for i, row in enumerate(rows["draws"])]
    fixed += [("noise", "—", result["noise"])]
    for kind, levels in rows["kinds"].items():
        fixed += [(kind, level, row) for level, row in levels.items()]
    for name, level, row in fixed:
        lines.append(f"| {name} | {level} | " + " | ".join(_cell(row.get(key)) for key in keys) + " |")
    lines += [
        "",
        f"## Which metric sees which corruption (level {result['levels'][-1]:g} against level 0)",
        "",
        "sees: it moves the right way by more than the noise (not monotone: some step between levels goes back); "
        "cannot see: it moves by no more than the noise; wrong way: it moves the other way by more than the noise.",
        "",
        "| kind | " + " | ".join(headers) + " |",
        "|---" * (len(keys) + 1) + "|",
    ]
    for kind, checks in result["checks"].items():
        lines.append(f"| {kind} | " + " | ".join(_verdict_cell(checks[key]) for key in keys) + " |")
    blind = [f"{key} / {kind} ({check['verdict']})" for kind, checks in result["checks"].items()
             for key, check in checks.items() if check["verdict"] not in ("sees", None)]  # fmt: skip
    lines += ["", "Blind spots: " + ("; ".join(blind) if blind else "none") + "."]
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", nargs="+", default=list(CORRUPTIONS), help=f"some of {', '.join(CORRUPTIONS)}")
    parser.add_argument("--levels", type=float, nargs="+", default=list(DEFAULT_LEVELS), help="in [0, 1]; 0 added")
    parser.add_argument("--metrics", default=DEFAULT_METRICS, help=f"subset of {DEFAULT_METRICS} (bench_generation's)")
    parser.add_argument("--noise-draws", type=int, default=2, help="other draws of uncorrupted scans: the noise")
    parser.add_argument("--seed", type=int, default=0, help="draws the scans and seeds the corruptions")
    add_scoring_arguments(parser, "the scans to corrupt (default: the other sequences)",
                          "the rings and columns of the corruptions and roughness", "runs/metric_validity")  # fmt: skip
    return parser.parse_args(argv)


def run(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.num < 1 or args.noise_draws < 1:
        raise InputError(f"--num and --noise-draws must be >= 1, got {args.num}, {args.noise_draws}")
    metrics = checked_metrics(args.metrics)
    args.kinds, args.levels = parse_kinds(args.kinds), parse_levels(args.levels)
    args.floor_sequences = args.floor_sequences or other_sequences(args.real, args.real_sequences)
    make_folder(args.out.parent)  # a file in the way: one line before the long computation
    torch.set_num_threads(1)
    args.geometry = beam_geometry(args.sensor)
    teacher = load_teacher(args.teacher) if "teacher" in metrics else None
    start = time.perf_counter()
    rows = validity_rows(args, metrics, teacher)
    keys = columns(metrics)
    noise, checks = checks_of(rows, keys)
    result = {
        "benchmark": "metric_validity",
        "command": "python benchmarks/metric_validity.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": host_info(),
        "real": str(args.real),
        "real_sequences": args.real_sequences,
        "floor_sequences": args.floor_sequences,
        "num": args.num,
        "seed": args.seed,
        "kinds": list(args.kinds),
        "levels": list(args.levels),
        "metrics": list(metrics),
        "keys": keys,
        "sign": {key: SIGN[key] for key in keys},
        "noise_draws": args.noise_draws,
        "teacher": str(args.teacher) if teacher else None,
        "extractors": {"frd": str(args.extractor_frd), "fpd": str(args.extractor_fpd)},
        "geometry": args.geometry,
        "rows": rows,
        "noise": noise,
        "checks": checks,
        "seconds": round(time.perf_counter() - start, 1),
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
