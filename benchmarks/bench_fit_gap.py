"""Fit vs generalisation of segmentation checkpoints: mIoU on the labelled scans the run trained on, on unseen
scans of the same places (the unlabeled part of its split) and on held-out places.

Says whether a run underfits (low mIoU on its own labelled scans), overfits (high there, low on unseen scans) or
meets a place gap (good on unseen scans of its places, low on held-out places) - and for a mean-teacher run,
whether self-training helped on the very scans it pseudo-labelled. Each checkpoint's own config names its data
root, label split and held-out sequences; `--weights ema` scores a semi run's teacher, `model` its student. Every
scan is scored whole (no subsampling, no augmentation, BatchNorm in eval mode) as `u4d seg-eval` does.

    python benchmarks/bench_fit_gap.py RUN_A/checkpoints/step_0000600.pt RUN_B/... [--scans 24] [--weights model]

Writes benchmarks/results/fit_gap.json (or --out).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from segmentation.config import SegTrainConfig
from segmentation.data import load_or_make_split
from segmentation.evaluate import accumulate, evenly_spaced, summary_of
from segmentation.models import build_model
from segmentation.train import class_names
from u4d_aug.config import config_from_dict
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[1]


def load_run(path: Path, weights: str) -> tuple[SegTrainConfig, int, torch.nn.Module]:
    """(run config, step, net with the chosen weights) of a seg-train checkpoint."""
    if not path.is_file():
        raise InputError(f"{path}: checkpoint not found (expected RUN/checkpoints/step_*.pt or RUN/model.pt)")
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(ckpt, dict) or "config" not in ckpt:
        raise InputError(f"{path}: not a seg-train checkpoint (no 'config')")
    if ckpt.get(weights) is None:
        raise InputError(f"{path}: no '{weights}' weights (ema exists only in checkpoints of mode 'semi' runs)")
    cfg = config_from_dict(SegTrainConfig, ckpt["config"], source=str(path))
    net = build_model(cfg.model)
    net.load_state_dict(ckpt[weights])
    return cfg, int(ckpt.get("step", -1)), net


def scan_sets(cfg: SegTrainConfig, limit: int) -> dict[str, tuple[ScanDataset, list[int]]]:
    """The three scan sets of a run: its labelled train scans, unseen scans of its places, held-out scans."""
    train = ScanDataset(cfg.data.root, cfg.data.train_sequences)
    labelled, unlabelled = load_or_make_split(
        cfg.data.root, train.entries, cfg.data.label_fraction, cfg.data.split_seed, cfg.data.split_mode
    )
    position = {entry: i for i, entry in enumerate(train.entries)}
    seen = [position[tuple(e)] for e in labelled]
    unseen = [position[tuple(e)] for e in unlabelled]
    held_out = ScanDataset(cfg.data.root, cfg.data.val_sequences, labeled_only=True)
    return {
        "labelled": (train, [seen[i] for i in evenly_spaced(len(seen), limit)]),
        "unseen_same_places": (train, [unseen[i] for i in evenly_spaced(len(unseen), limit)]),
        "held_out_places": (held_out, evenly_spaced(len(held_out), limit)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+")
    parser.add_argument("--scans", type=int, default=24, help="scans per set, evenly spaced")
    parser.add_argument("--weights", choices=["model", "ema"], default="model")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "fit_gap.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    try:
        for path in args.checkpoints:
            cfg, step, net = load_run(path, args.weights)
            row = {"checkpoint": str(path), "weights": args.weights, "step": step, "mode": cfg.mode, "sets": {}}
            for name, (dataset, indices) in scan_sets(cfg, args.scans).items():
                cm, calibration = accumulate(net, dataset, indices, torch.device("cpu"), cfg.model.num_classes)
                summary = summary_of(cm, calibration, class_names(cfg))
                row["sets"][name] = {
                    "scans": len(indices),
                    "miou": summary["miou"],
                    "ece_per_scan": summary["ece_per_scan"],
                }
            rows.append(row)
    except InputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{'run':<40} {'step':>5} {'labelled':>9} {'unseen':>9} {'held-out':>9}   (mIoU %, {args.weights} weights)")
    for row in rows:
        path = Path(row["checkpoint"])
        run = path.parent.parent if path.parent.name == "checkpoints" else path.parent  # RUN/checkpoints/x.pt
        figures = " ".join(f"{100 * row['sets'][name]['miou']:9.1f}" for name in row["sets"])
        print(f"{'/'.join(run.parts[-3:]):<40} {row['step']:>5} {figures}")
    atomic_write_json(args.out, {"command": " ".join(["python", *sys.argv]), "scans": args.scans, "runs": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
