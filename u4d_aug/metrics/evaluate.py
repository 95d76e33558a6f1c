"""`u4d evaluate`: the paper's Table 1 (FRD, FPD, JSD, MMD) and Table 2 (TTCE, CTC) for a bank of scans vs real ones.

Both folders are SemanticKITTI-layout roots (`sequences/XX/velodyne/*.bin`); a generated bank may lack labels and
poses. Table 1 follows R2DM `evaluate.py` (generation_protocols.md §3.1): FRD/FPD are Fréchet distances of the
trained extractors' features (u4d_aug.metrics.extractors; each value records its extractor hash), JSD/MMD are the
BEV metrics (u4d_aug.metrics.bev; MMD printed x1e4). Table 2 follows the U4D/LC temporal protocol
(u4d_aug.metrics.temporal) per sequence with `poses.txt` + `calib.txt`, pooled over sequences; a table that
cannot be computed says why.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from u4d_aug.bank import read_manifest
from u4d_aug.data.datasets import expand_sequences, list_frames, list_sequences
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json, atomic_write_text, make_folder
from u4d_aug.metrics import bev, temporal
from u4d_aug.progress import progress_bar

METRICS = ("frd", "fpd", "jsd", "mmd", "points", "rangejs", "intensityjs", "ttce", "ttce_global", "ctc")
TABLE1 = ("frd", "fpd", "jsd", "mmd", "points", "rangejs", "intensityjs")
STATISTICS = ("points", "rangejs", "intensityjs")  # Table-1 entries read from the scans' own statistics
RANGE_BINS = np.arange(0.0, 81.0, 1.0)  # 1 m bins over 0-80 m for the range-histogram JS distance
# 0.02 bins over the layout's [0, 1] intensity for the intensity-histogram JS distance (a segmentor reads intensity
# as a feature: a bank whose intensities sit elsewhere is a domain shift that the geometric metrics do not see)
INTENSITY_BINS = np.linspace(0.0, 1.0, 51)
TABLE2 = ("ttce", "ttce_global", "ctc")  # ttce_global: TTCE with ICP from a global registration (not LC)


def parse_metrics(text: str) -> tuple[str, ...]:
    """'jsd,mmd' -> ('jsd', 'mmd'); InputError naming the allowed metrics for anything else."""
    names = tuple(dict.fromkeys(part.strip().lower() for part in text.split(",") if part.strip()))
    unknown = [name for name in names if name not in METRICS]
    if not names or unknown:
        raise InputError(f"--metrics {text!r}: expected a comma-separated subset of {','.join(METRICS)}")
    return names


def list_scans(
    root: str | Path, max_scans: int | None = None, sequences: list[str] | None = None
) -> list[tuple[str, str, Path]]:
    """(seq, frame, path) of the first `max_scans` scans of `sequences` (names or 'A-B' ranges; None = all)."""
    root = Path(root)
    present = list_sequences(root)
    sequences = expand_sequences(sequences) if sequences else None  # '00-11' ranges as in configs
    missing = [s for s in sequences or [] if s not in present]
    if missing:
        raise InputError(f"{root}: sequence(s) {', '.join(missing)} not found; present: {', '.join(present)}")
    entries = [
        (seq, frame, root / "sequences" / seq / "velodyne" / f"{frame}.bin")
        for seq in (sequences or present)
        for frame in list_frames(root, seq)
    ]
    if not entries:
        raise InputError(f"{root}: no scans under sequences/*/velodyne/")
    if max_scans is not None:
        if max_scans < 1:
            raise InputError(f"--max-scans: expected a positive count, got {max_scans}")
        entries = entries[:max_scans]
    return entries


def _scans(entries: list[tuple[str, str, Path]], what: str, progress: bool) -> Any:
    """`entries` with a progress bar over their scans, titled `what` ("BEV bank", ...), when `progress`."""
    return progress_bar(entries, desc=what, unit="scan", enabled=progress, leave=False)


def _window(points: np.ndarray) -> np.ndarray:
    """Points inside the 0.5-63 m evaluation window (R2DM/LiDARGen), applied to both sides before FRD/FPD."""
    depth2 = np.einsum("ij,ij->i", points[:, :3], points[:, :3])
    return points[(depth2 >= bev.EVAL_MIN_DEPTH**2) & (depth2 <= bev.EVAL_MAX_DEPTH**2)]


def _stream_features(
    extractor: Any, entries: list[tuple[str, str, Path]], batch_size: int = 8, what: str = "", progress: bool = False
) -> dict[str, np.ndarray]:
    """Features of windowed scans read batch by batch (a 10k-scan bank never sits in memory at once)."""
    from u4d_aug.metrics.extractors import extract_features

    parts = []
    with progress_bar(total=len(entries), desc=what, unit="scan", enabled=progress, leave=False) as bar:
        for start in range(0, len(entries), batch_size):
            scans = [_window(read_kitti_scan(path)) for _, _, path in entries[start : start + batch_size]]
            parts.append(extract_features(extractor, scans, batch_size))
            bar.update(len(scans))
    return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}


def _feature_metric(
    name: str,
    checkpoint: str | Path | None,
    bank: list[tuple[str, str, Path]],
    real: list[tuple[str, str, Path]],
    progress: bool = False,
) -> dict[str, Any]:
    """FRD or FPD entry: Fréchet distance of extractor features, with the extractor hash and path."""
    from u4d_aug.metrics.extractors import load_extractor
    from u4d_aug.metrics.frechet import frechet_from_features

    if checkpoint is None:
        return {"value": None, "missing": f"no --extractor-{name} checkpoint given (train one: u4d train-extractor)"}
    extractor = load_extractor(checkpoint)
    if extractor.kind != name:
        raise InputError(f"--extractor-{name} {checkpoint}: this checkpoint is a {extractor.kind} extractor")
    if len(bank) < 2 or len(real) < 2:
        return {"value": None, "missing": "needs at least 2 scans on each side", "extractor_hash": extractor.hash}
    feats_bank = _stream_features(extractor, bank, what=f"{name} bank", progress=progress)
    feats_real = _stream_features(extractor, real, what=f"{name} real", progress=progress)
    entry: dict[str, Any] = {
        "value": frechet_from_features(feats_real[name], feats_bank[name]),
        "feature_dim": int(feats_bank[name].shape[1]),
        "extractor_hash": extractor.hash,
        "extractor_path": str(checkpoint),
    }
    if name == "frd":
        entry["pooled_value"] = frechet_from_features(feats_real["frd_pooled"], feats_bank["frd_pooled"])
        entry["pooled_dim"] = int(feats_bank["frd_pooled"].shape[1])
    return entry


def scan_statistics(
    entries: list[tuple[str, str, Path]], what: str = "", progress: bool = False
) -> dict[str, np.ndarray]:
    """Points per scan "points" (S,), pooled histograms of point ranges over `RANGE_BINS` "rangejs" (80,) and of
    intensities (clipped to [0, 1]) over `INTENSITY_BINS` "intensityjs" (50,) of the scans."""
    counts = []
    ranges = np.zeros(len(RANGE_BINS) - 1, dtype=np.int64)
    intensities = np.zeros(len(INTENSITY_BINS) - 1, dtype=np.int64)
    for _, _, path in _scans(entries, what, progress):
        points = read_kitti_scan(path)  # (N, 4) x, y, z, intensity
        counts.append(points.shape[0])
        ranges += np.histogram(np.linalg.norm(points[:, :3], axis=1), RANGE_BINS)[0]
        intensities += np.histogram(np.clip(points[:, 3], 0.0, 1.0), INTENSITY_BINS)[0]
    return {"points": np.asarray(counts), "rangejs": ranges, "intensityjs": intensities}


def _statistic_metric(name: str, bank: dict[str, np.ndarray], real: dict[str, np.ndarray]) -> dict[str, Any]:
    """points: mean points per scan of the bank (and of the real scans); rangejs / intensityjs: JS distance of the
    pooled range / intensity pmfs. `bank`, `real`: `scan_statistics` of each side."""
    from scipy.spatial.distance import jensenshannon

    if name == "points":
        counts_bank, counts_real = bank["points"], real["points"]
        value = float(counts_bank.mean())
        return {"value": value, "std": float(counts_bank.std()), "real": float(counts_real.mean()),
                "ratio_to_real": value / max(float(counts_real.mean()), 1.0)}  # fmt: skip
    hist_bank, hist_real = bank[name], real[name]
    if hist_bank.sum() == 0 or hist_real.sum() == 0:
        return {"value": None, "missing": "no points on one side"}
    value = float(jensenshannon(hist_real / hist_real.sum(), hist_bank / hist_bank.sum()))
    bins = "1 m bins over 0-80 m" if name == "rangejs" else "0.02 bins over intensity 0-1"
    entry: dict[str, Any] = {"value": value, "unit": f"JS distance (natural log), {bins}"}
    if name == "intensityjs":  # where the mass sits: mean intensity of each side (bin centres)
        centres = (INTENSITY_BINS[:-1] + INTENSITY_BINS[1:]) / 2
        entry["mean"] = float(hist_bank @ centres / hist_bank.sum())
        entry["real_mean"] = float(hist_real @ centres / hist_real.sum())
    return entry


def _temporal_table(
    root: Path, entries: list[tuple[str, str, Path]], metrics: tuple[str, ...], what: str = "", progress: bool = False
) -> dict[str, Any]:
    """TTCE (m) and CTC (m^2) per interval pooled over the sequences of `entries`, or the reason it is missing."""
    manifest = root / "manifest.json"
    if manifest.is_file() and (read_manifest(root) or {}).get("placeholder_poses"):
        return {"missing": f"{manifest}: the bank's poses.txt are identity placeholders, no ground-truth poses"}
    by_seq: dict[str, list[int]] = {}
    for seq, frame, _ in entries:
        if not frame.isdigit():
            return {"missing": f"{root}/sequences/{seq}: frame name {frame!r} is not a number"}
        by_seq.setdefault(seq, []).append(int(frame))
    for seq, frames in by_seq.items():
        folder = root / "sequences" / seq
        for name in ("poses.txt", "calib.txt"):
            if not (folder / name).is_file():
                return {"missing": f"{folder / name} not found: temporal metrics need ground-truth poses"}
        if np.any(np.diff(frames) != 1):
            return {"missing": f"{folder}: frames are not consecutive; temporal intervals need consecutive frames"}
    ttce_scores, global_scores, ctc_scores = [], [], []
    seconds = {"ttce": 0.0, "ttce_global": 0.0, "ctc": 0.0}
    for seq, frames in progress_bar(by_seq.items(), desc=what, unit="sequence", enabled=progress, leave=False):
        scans, poses = temporal.load_kitti_sequence(root / "sequences" / seq, frames)
        if "ttce" in metrics:
            start = time.perf_counter()
            ttce_scores.append(temporal.ttce(scans, poses))
            seconds["ttce"] += time.perf_counter() - start
        if "ttce_global" in metrics:
            start = time.perf_counter()
            global_scores.append(temporal.ttce(scans, poses, registration="global"))
            seconds["ttce_global"] += time.perf_counter() - start
        if "ctc" in metrics:
            start = time.perf_counter()
            ctc_scores.append(temporal.ctc(scans, poses))
            seconds["ctc"] += time.perf_counter() - start
    table: dict[str, Any] = {"sequences": sorted(by_seq), "scans": len(entries)}
    for name, scores in (("ttce", ttce_scores), ("ttce_global", global_scores), ("ctc", ctc_scores)):
        if name in metrics:
            merged = temporal.merge_interval_scores(scores)
            table[name] = {str(k): _finite(v) for k, v in merged.mean.items()}
            table[f"{name}_pairs"] = {str(k): len(v) for k, v in merged.per_pair.items()}
            table[f"{name}_seconds"] = seconds[name]
    return table


def _finite(value: float) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def evaluate(
    bank: str | Path,
    real: str | Path,
    metrics: tuple[str, ...] = METRICS,
    max_scans: int | None = None,
    extractor_frd: str | Path | None = None,
    extractor_fpd: str | Path | None = None,
    real_sequences: list[str] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Table 1 (bank vs real) and Table 2 (temporal, bank and real) as one json-ready result (progress bars over the
    scans of each pass when `progress`)."""
    bank, real = Path(bank), Path(real)
    bank_entries, real_entries = list_scans(bank, max_scans), list_scans(real, max_scans, real_sequences)
    result: dict[str, Any] = {
        "bank": str(bank),
        "real": str(real),
        "counts": {"bank": len(bank_entries), "real": len(real_entries)},
        "real_sequences": sorted({seq for seq, _, _ in real_entries}),
        "config": _evaluation_settings(metrics, max_scans),
        "table1": {},
        "table2": {},
        "seconds": {},
    }
    wanted1 = [m for m in TABLE1 if m in metrics]
    if wanted1:
        extractors = {"frd": extractor_frd, "fpd": extractor_fpd}
        result["table1"] = _table1(wanted1, bank_entries, real_entries, extractors, result["seconds"], progress)
    wanted2 = tuple(m for m in TABLE2 if m in metrics)
    if wanted2:
        result["table2"]["bank"] = _temporal_table(bank, bank_entries, wanted2, "temporal bank", progress)
        if bank.resolve() == real.resolve() and bank_entries == real_entries:
            result["table2"]["real"] = result["table2"]["bank"]  # same scans: computed once
        else:
            result["table2"]["real"] = _temporal_table(real, real_entries, wanted2, "temporal real", progress)
    return result


def _evaluation_settings(metrics: tuple[str, ...], max_scans: int | None) -> dict[str, Any]:
    """The protocol of an evaluation as its result records it: metrics, scan cap, windows, bins and ICP settings."""
    return {
        "metrics": list(metrics),
        "max_scans": max_scans,
        "eval_window_m": [bev.EVAL_MIN_DEPTH, bev.EVAL_MAX_DEPTH],
        "bev": {
            "range_m": [bev.BEV_MIN_DEPTH, bev.BEV_MAX_DEPTH],
            "field_m": bev.BEV_FIELD_SIZE,
            "bins": bev.BEV_BINS,
            "mmd_sigma": bev.MMD_SIGMA,
            "mmd_scale": bev.MMD_REPORT_SCALE,
        },
        "ttce": {
            "intervals": list(temporal.TTCE_INTERVALS),
            "max_correspondence_m": temporal.MAX_CORRESPONDENCE,
            "voxel_size_m": temporal.TTCE_VOXEL_SIZE,
            "min_range_m": temporal.MIN_RANGE,
        },
        "ttce_global": {
            "intervals": list(temporal.TTCE_INTERVALS),
            "feature_voxel_m": temporal.GLOBAL_VOXEL_SIZE,
            "ransac_iterations": temporal.GLOBAL_RANSAC_ITERATIONS,
        },
        "ctc": {"intervals": list(temporal.CTC_INTERVALS), "min_range_m": temporal.MIN_RANGE},
    }


def _table1(
    wanted: list[str],
    bank_entries: list[tuple[str, str, Path]],
    real_entries: list[tuple[str, str, Path]],
    extractors: dict[str, str | Path | None],
    seconds: dict[str, float],
    progress: bool,
) -> dict[str, Any]:
    """Table 1 entries of the `wanted` metrics, bank vs real; the seconds each took go to `seconds` (BEV
    histograms, read once for JSD and MMD, under "bev_histograms")."""
    if "jsd" in wanted or "mmd" in wanted:
        start = time.perf_counter()
        bank_scans = _scans(bank_entries, "BEV bank", progress)
        real_scans = _scans(real_entries, "BEV real", progress)
        hist_bank = bev.bev_histograms(read_kitti_scan(path) for _, _, path in bank_scans)  # (S_b, 100, 100)
        hist_real = bev.bev_histograms(read_kitti_scan(path) for _, _, path in real_scans)  # (S_r, 100, 100)
        seconds["bev_histograms"] = time.perf_counter() - start
    if any(name in STATISTICS for name in wanted):
        stats_bank = scan_statistics(bank_entries, "statistics bank", progress)
        stats_real = scan_statistics(real_entries, "statistics real", progress)
    table = {}
    for name in wanted:
        start = time.perf_counter()
        if name == "jsd":
            table[name] = {"value": bev.bev_jsd(hist_real, hist_bank), "unit": "JS distance (natural log)"}
        elif name == "mmd":
            raw = bev.bev_mmd(hist_real, hist_bank)
            table[name] = {"value": raw * bev.MMD_REPORT_SCALE, "raw": raw, "unit": "x1e-4"}
        elif name in STATISTICS:
            table[name] = _statistic_metric(name, stats_bank, stats_real)
        else:
            table[name] = _feature_metric(name, extractors[name], bank_entries, real_entries, progress)
        seconds[name] = time.perf_counter() - start
    return table


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "—"
    return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.1f}"


def to_markdown(result: dict[str, Any]) -> str:
    """Markdown report: Table 1, Table 2, sample counts, extractor hashes, missing reasons and config."""
    lines = [
        "# Generation metrics",
        "",
        f"bank: `{result['bank']}` ({result['counts']['bank']} scans); "
        f"real: `{result['real']}` ({result['counts']['real']} scans)",
        "",
    ]
    table1 = result["table1"]
    if table1:
        names = list(table1)
        header = {"frd": "FRD ↓", "fpd": "FPD ↓", "jsd": "JSD ↓", "mmd": "MMD ×10⁴ ↓", "points": "points/scan",
                  "rangejs": "range JS ↓", "intensityjs": "intensity JS ↓"}  # fmt: skip
        lines += ["## Table 1: distribution metrics (bank vs real)", ""]
        lines += ["| | " + " | ".join(header[n] for n in names) + " |", "|---" * (len(names) + 1) + "|"]
        lines += ["| bank | " + " | ".join(_fmt(table1[n].get("value")) for n in names) + " |", ""]
        for name in names:
            entry = table1[name]
            if entry.get("missing"):
                lines.append(f"- {name.upper()} missing: {entry['missing']}")
            if entry.get("extractor_hash"):
                extra = (
                    f", pooled {_fmt(entry['pooled_value'])} ({entry['pooled_dim']}-D)"
                    if "pooled_value" in entry
                    else ""
                )
                dim = f"{entry['feature_dim']}-D features" if "feature_dim" in entry else "no features"
                lines.append(f"- {name.upper()}: extractor `{entry['extractor_hash']}` ({dim}{extra})")
        lines.append("")
    table2 = result["table2"]
    if table2:
        lines += ["## Table 2: temporal consistency", ""]
        ttce_k = [str(k) for k in result["config"]["ttce"]["intervals"]]
        ctc_k = [str(k) for k in result["config"]["ctc"]["intervals"]]
        scored = [name for name in TABLE2 if name in result["config"]["metrics"]]
        head = {"ttce": "TTCE", "ttce_global": "TTCE-global", "ctc": "CTC"}
        columns = [(name, k) for name in scored for k in (ctc_k if name == "ctc" else ttce_k)]
        cols = [f"{head[n]} k={k} ({'m²' if n == 'ctc' else 'm'}) ↓" for n, k in columns]
        lines += ["| | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
        notes = []
        for side in ("bank", "real"):
            table = table2.get(side, {})
            if "missing" in table:
                lines.append(f"| {side} | " + " | ".join("—" for _ in cols) + " |")
                notes.append(f"- {side} temporal metrics missing: {table['missing']}")
                continue
            values = [table.get(name, {}).get(k) for name, k in columns]
            lines.append(f"| {side} | " + " | ".join(_fmt(v) for v in values) + " |")
            pairs = {name: table.get(f"{name}_pairs") for name in TABLE2 if f"{name}_pairs" in table}
            notes.append(f"- {side}: sequences {', '.join(table['sequences'])}, {table['scans']} scans, pairs {pairs}")
        lines += ["", *notes, ""]
    lines += ["## Config", "", "```json", json.dumps(result["config"], indent=1), "```", ""]
    return "\n".join(lines)


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """`u4d evaluate --bank DIR --real DIR [--metrics ...] [--json] [--md] [--out DIR] ...`."""
    parser.add_argument("--bank", type=Path, required=True, help="generated scans, SemanticKITTI layout")
    parser.add_argument("--real", type=Path, required=True, help="real scans, SemanticKITTI layout")
    parser.add_argument("--metrics", default=",".join(METRICS), help=f"comma-separated subset of {','.join(METRICS)}")
    parser.add_argument("--json", action="store_true", help="write OUT/evaluation.json")
    parser.add_argument("--md", action="store_true", help="write OUT/evaluation.md")
    parser.add_argument("--out", type=Path, default=Path("runs/evaluate"), help="folder for --json/--md")
    parser.add_argument("--max-scans", type=int, default=None, help="first N scans of each root (sorted)")
    parser.add_argument(
        "--real-sequences", nargs="+", default=None, help="only these sequences of --real (held out; A-B ranges too)"
    )
    parser.add_argument("--extractor-frd", type=Path, default=None, help="FRD extractor checkpoint (frd.pt)")
    parser.add_argument("--extractor-fpd", type=Path, default=None, help="FPD extractor checkpoint (fpd.pt)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run_evaluate(args: argparse.Namespace) -> int:
    """Compute, print the markdown tables, write json/md atomically when asked (NaN as null in the json)."""
    if args.max_scans is not None and args.max_scans < 1:
        raise InputError(f"--max-scans must be >= 1, got {args.max_scans}")
    if args.json or args.md:
        make_folder(args.out)  # a file or an unwritable place in the way: one line before the long computation
    result = evaluate(
        args.bank,
        args.real,
        parse_metrics(args.metrics),
        args.max_scans,
        args.extractor_frd,
        args.extractor_fpd,
        args.real_sequences,
        progress=not args.no_progress,
    )
    text = to_markdown(result)
    print(text)
    if args.json:
        atomic_write_json(args.out / "evaluation.json", result)
    if args.md:
        atomic_write_text(args.out / "evaluation.md", text)
    return 0
