"""Fit vs generalisation of segmentation checkpoints: mIoU on the labelled scans the run trained on, on unseen
scans of the same places (the unlabeled part of its split) and on held-out places.

Says whether a run underfits (low mIoU on its own labelled scans), overfits (high there, low on unseen scans) or
meets a place gap (good on unseen scans of its places, low on held-out places) - and for a mean-teacher run,
whether self-training helped on the very scans it pseudo-labelled. Each checkpoint's own config names its data
root, label split and held-out sequences; `--weights ema` scores a semi run's teacher, `model` its student. Every
scan is scored whole (no subsampling, no augmentation, BatchNorm in eval mode) as `u4d seg-eval` does.

    python benchmarks/diagnostics/bench_fit_gap.py RUN_A/checkpoints/step_0000600.pt RUN_B/... \
        [--scans 24] [--weights model]

Writes benchmarks/results/segmentation/fit_gap.json (or --out).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from segmentation.batches import train_scans
from segmentation.config import SegTrainConfig, class_names
from segmentation.evaluate import accumulate, evenly_spaced, summary_of
from segmentation.predict import load_checkpoint, model_from_checkpoint
from segmentation.semi import unlabeled_stream
from u4d_aug.config import saved_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.distributed import DistInfo
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[2]
CPU = torch.device("cpu")


def load_run(path: Path, weights: str) -> tuple[SegTrainConfig, int, torch.nn.Module]:
    """(run config, step, net with the chosen weights) of a seg-train checkpoint."""
    ckpt = load_checkpoint(path)
    if ckpt.get(weights) is None:
        raise InputError(f"{path}: no '{weights}' weights (ema exists only in checkpoints of mode 'semi' runs)")
    cfg = saved_config(SegTrainConfig, ckpt["config"], str(path))
    net = model_from_checkpoint({**ckpt, "model": ckpt[weights]}, CPU, source=str(path))
    return cfg, int(ckpt.get("step", -1)), net


def scan_sets(cfg: SegTrainConfig, limit: int) -> dict[str, tuple[ScanDataset, list[int]]]:
    """The three scan sets of a run, as its training drew them: its labelled scans, the labelled scans among its
    unlabeled split (unseen scans of its places), and the held-out scans."""
    labelled = train_scans(cfg, DistInfo(0, 1, 0, CPU))
    with_labels = set(ScanDataset(cfg.data.root, cfg.data.train_sequences, labeled_only=True).entries)
    unseen = unlabeled_stream(cfg).sources[0]  # the unlabeled part of the split
    unseen.entries = [entry for entry in unseen.entries if entry in with_labels]
    held_out = ScanDataset(cfg.data.root, cfg.data.val_sequences, labeled_only=True)
    return {
        name: (dataset, evenly_spaced(len(dataset), limit))
        for name, dataset in (("labelled", labelled), ("unseen_same_places", unseen), ("held_out_places", held_out))
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+")
    parser.add_argument("--scans", type=int, default=24, help="scans per set, evenly spaced")
    parser.add_argument("--weights", choices=["model", "ema"], default="model")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "fit_gap.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    try:
        for path in args.checkpoints:
            cfg, step, net = load_run(path, args.weights)
            row = {"checkpoint": str(path), "weights": args.weights, "step": step, "mode": cfg.mode, "sets": {}}
            for name, (dataset, indices) in scan_sets(cfg, args.scans).items():
                cm, calibration = accumulate(net, dataset, indices, CPU, cfg.model.num_classes, progress=True)
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
