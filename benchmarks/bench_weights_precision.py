"""What shipping a segmentor in float16 or int8 (`u4d export-weights [--int8]`) changes in U4D's uncertain region.

    python benchmarks/bench_weights_precision.py runs/unc_seg/model.pt data/sim_eval --scans 12 \
        --out benchmarks/results/segmentation/weights_precision_segmentor.json

The float32 training checkpoint is exported to float16 and to int8 (temp folder), the three nets predict the
same held-out scans (`--scans` evenly spaced of `--sequences`), and per scan against float32:
- topk_overlap: share of the float32 P_u (top `--k` entropy points, `u4d_aug.uncertainty.select_uncertain`) that
  the exported net also selects; what stage 1 and stage 2 are conditioned on,
- argmax_agree: share of points with the same predicted class,
- max_abs: largest |probability difference| over points and classes,
plus file sizes. Medians and minima over scans go in the json and the .md beside it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from segmentation.predict import load_checkpoint, model_from_checkpoint, scan_probs
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.errors import InputError
from u4d_aug.export_weights import export_weights
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text
from u4d_aug.uncertainty import select_uncertain

PRECISIONS = ("float16", "int8")
METRICS = ("topk_overlap", "argmax_agree", "max_abs")


def compare(reference: np.ndarray, other: np.ndarray, k: float) -> dict[str, float]:
    """topk_overlap, argmax_agree, max_abs of (N, K) probabilities `other` against `reference`."""
    chosen = set(select_uncertain(reference, k).tolist())
    overlap = len(chosen & set(select_uncertain(other, k).tolist())) / max(len(chosen), 1)
    return {
        "topk_overlap": overlap,
        "argmax_agree": float((reference.argmax(1) == other.argmax(1)).mean()),
        "max_abs": float(np.abs(reference - other).max()),
    }


def run(checkpoint: Path, root: Path, sequences: list[str] | None, scans: int, k: float) -> dict:
    """Export, predict, compare; returns the json record."""
    torch.set_num_threads(1)
    cpu = torch.device("cpu")
    with tempfile.TemporaryDirectory() as tmp:
        files = {"float32": checkpoint}
        for precision in PRECISIONS:
            files[precision] = Path(tmp) / f"{precision}.pt"
            export_weights(checkpoint, files[precision], int8=precision == "int8")
        sizes = {name: path.stat().st_size for name, path in files.items()}
        models = {name: model_from_checkpoint(load_checkpoint(path), cpu) for name, path in files.items()}
    dataset = ScanDataset(root, sequences)
    if len(dataset) == 0:
        raise InputError(f"{root}: no scans in sequences {sequences}")
    picks = np.unique(np.linspace(0, len(dataset) - 1, num=min(scans, len(dataset))).round().astype(int))
    rows = []
    for index in picks:
        points = dataset[int(index)]["points"]
        probs = {name: scan_probs(m, points, cpu, m.cfg.num_classes).astype(np.float32) for name, m in models.items()}
        row = {"scan": "/".join(dataset.entries[int(index)])}
        for precision in PRECISIONS:
            row[precision] = compare(probs["float32"], probs[precision], k)
        rows.append(row)
        print(row, flush=True)
    summary = {
        precision: {
            metric: {
                "median": statistics.median(r[precision][metric] for r in rows),
                "worst": (max if metric == "max_abs" else min)(r[precision][metric] for r in rows),
            }
            for metric in METRICS
        }
        for precision in PRECISIONS
    }
    return {
        "checkpoint": str(checkpoint),
        "k": k,
        "bytes": sizes,
        "summary": summary,
        "scans": rows,
        "host": host_info(),
    }


def markdown(record: dict) -> str:
    """The table of the .md beside the json."""
    lines = [
        "# Segmentor weights in float16 / int8 against float32",
        "",
        f"{len(record['scans'])} held-out scans; P_u = top {100 * record['k']:g} % entropy; median (worst scan).",
        "",
        "| weights | file MB | P_u overlap % | argmax agreement % | max abs prob. diff. |",
        "|---|---|---|---|---|",
        f"| float32 (training checkpoint) | {record['bytes']['float32'] / 1e6:.2f} | 100 | 100 | 0 |",
    ]
    for precision in PRECISIONS:
        s = record["summary"][precision]
        lines.append(
            f"| {precision} | {record['bytes'][precision] / 1e6:.2f} | "
            f"{100 * s['topk_overlap']['median']:.2f} ({100 * s['topk_overlap']['worst']:.2f}) | "
            f"{100 * s['argmax_agree']['median']:.2f} ({100 * s['argmax_agree']['worst']:.2f}) | "
            f"{s['max_abs']['median']:.3f} ({s['max_abs']['worst']:.3f}) |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="seg-train checkpoint (model.pt, float32)")
    parser.add_argument("root", type=Path, help="SemanticKITTI-layout root of held-out scans")
    parser.add_argument("--sequences", nargs="*", default=None)
    parser.add_argument("--scans", type=int, default=12)
    parser.add_argument("--k", type=float, default=0.1, help="P_u fraction")
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/segmentation/weights_precision_segmentor.json")
    )
    args = parser.parse_args(argv)
    try:
        record = run(args.checkpoint, args.root, args.sequences, args.scans, args.k)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    atomic_write_json(args.out, record)
    atomic_write_text(args.out.with_suffix(".md"), markdown(record))
    print(markdown(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
