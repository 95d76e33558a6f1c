"""How much harder a LaserMix scan is for a segmentor than the scans it was cut from (a diagnostic of the mean teacher).

Pairs of labelled training scans (a, b) are mixed as the mean-teacher step mixes a labelled with an unlabeled scan
(`segmentation.lasermix.lasermix`, the run's sensor pitch range), here with ground truth on both sides, so every
point of a mixed scan is scored against its own label. The net (student weights of a training checkpoint, eval
mode) labels each scan alone and each mixed scan; per number of areas n the table gives point accuracy, cross-entropy
and mIoU over the same points, alone vs mixed. Scans are thinned to the run's data.max_points as in training, with
no other augmentation.

    python benchmarks/diagnostics/bench_lasermix_context.py RUN/burn_in.pt [--pairs 8] [--areas 2 3 4 5 6]

Writes benchmarks/results/segmentation/lasermix_context.json (or --out).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from segmentation.batches import train_scans
from segmentation.config import SegTrainConfig
from segmentation.data import training_subset
from segmentation.lasermix import lasermix
from segmentation.metrics import confusion_matrix, iou_per_class, mean_iou
from segmentation.predict import load_checkpoint, model_from_checkpoint
from segmentation.semi import pitch_range
from u4d_aug.config import saved_config
from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, SEMANTICKITTI_IGNORE
from u4d_aug.distributed import DistInfo
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[2]
K = len(SEMANTICKITTI_CLASSES)


def scores(logits: torch.Tensor, target: torch.Tensor) -> dict:
    """Point accuracy, mean CE and the confusion matrix (K, K) over the labelled points."""
    valid = target != SEMANTICKITTI_IGNORE
    logits, target = logits[valid], target[valid]
    return {
        "points": int(valid.sum()),
        "correct": int((logits.argmax(1) == target).sum()),
        "ce_sum": float(F.cross_entropy(logits.float(), target, reduction="sum")),
        "confusion": confusion_matrix(logits.argmax(1), target, K),
    }


def merge(parts: list[dict]) -> dict:
    """Accuracy %, CE, mIoU % (classes present) and IoU % per class present of summed per-batch scores."""
    points = sum(p["points"] for p in parts)
    confusion = sum(p["confusion"] for p in parts)
    present = confusion.sum(axis=1) > 0  # (K,) classes with ground-truth points
    return {
        "points": points,
        "accuracy": 100.0 * sum(p["correct"] for p in parts) / points,
        "ce": sum(p["ce_sum"] for p in parts) / points,
        "miou": 100.0 * mean_iou(confusion),
        "iou": {
            name: 100.0 * float(iou)
            for name, iou, kept in zip(SEMANTICKITTI_CLASSES, iou_per_class(confusion), present)
            if kept
        },
        "class_points": {name: int(n) for name, n in zip(SEMANTICKITTI_CLASSES, confusion.sum(axis=1)) if n > 0},
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="a seg-train checkpoint (student weights under 'model')")
    parser.add_argument("--pairs", type=int, default=8, help="scan pairs (2 x pairs labelled scans)")
    parser.add_argument("--areas", type=int, nargs="+", default=[2, 3, 4, 5, 6])
    parser.add_argument("--seed", type=int, default=0, help="which scans, subsamples and pairings")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    parser.add_argument(
        "--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "lasermix_context.json"
    )
    args = parser.parse_args()
    if args.pairs < 1 or min(args.areas) < 1:
        parser.error(f"--pairs and --areas must be >= 1; got --pairs {args.pairs}, --areas {args.areas}")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    try:
        ckpt = load_checkpoint(args.checkpoint)
        cfg = saved_config(SegTrainConfig, ckpt["config"], str(args.checkpoint))
        scans = train_scans(cfg, DistInfo(rank=0, world_size=1, local_rank=0, device=torch.device("cpu")))
        if len(scans) < 2 * args.pairs:
            raise InputError(
                f"{cfg.data.root}: {len(scans)} labelled training scans, --pairs {args.pairs} needs {2 * args.pairs}"
            )
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    model = model_from_checkpoint(ckpt, torch.device("cpu"), source=str(args.checkpoint))
    generator = torch.Generator().manual_seed(args.seed)
    picks = torch.randperm(len(scans), generator=generator)[: 2 * args.pairs].tolist()
    loaded = []
    for index in picks:
        item = scans[index]
        points, labels = torch.from_numpy(item["points"]), torch.from_numpy(item["labels"]).long()
        keep = training_subset(points, cfg.data.sector_deg, cfg.data.max_points, generator)
        loaded.append((points[keep], labels[keep]))
    pairs = list(zip(loaded[0::2], loaded[1::2]))

    rows = []
    with torch.no_grad():
        alone = [scores(model([p]), y) for p, y in loaded]
        rows.append({"areas": None, **merge(alone)})
        for n in args.areas:
            mixed = []
            for (p_a, y_a), (p_b, y_b) in pairs:
                m1, l1, m2, l2 = lasermix(p_a, y_a, p_b, y_b, [n], pitch_range(cfg), generator=generator)
                mixed += [scores(model([m1]), l1), scores(model([m2]), l2)]
            rows.append({"areas": n, **merge(mixed)})

    print(
        f"{args.checkpoint} (step {ckpt['step']}): {len(loaded)} labelled scans of {cfg.data.root}, {len(pairs)} pairs"
    )
    print(f"{'scans':>14} {'points':>8} {'accuracy %':>10} {'CE':>6} {'mIoU %':>7}")
    for row in rows:
        name = "alone" if row["areas"] is None else f"mixed, {row['areas']} areas"
        print(f"{name:>14} {row['points']:>8} {row['accuracy']:>10.1f} {row['ce']:>6.3f} {row['miou']:>7.1f}")
    print(f"\nIoU % per class present ({len(rows[0]['iou'])} classes)")
    heads = ["alone" if r["areas"] is None else f"{r['areas']} areas" for r in rows]
    print(f"{'class':>14} {'points':>8} " + " ".join(f"{head:>8}" for head in heads))
    for name, count in rows[0]["class_points"].items():
        print(f"{name:>14} {count:>8} " + " ".join(f"{r['iou'][name]:>8.1f}" for r in rows))
    atomic_write_json(args.out, {
        "command": "python benchmarks/diagnostics/bench_lasermix_context.py " + " ".join(sys.argv[1:]),
        "checkpoint": str(args.checkpoint),
        "step": int(ckpt["step"]),
        "max_points": cfg.data.max_points,
        "pitch_range_deg": list(pitch_range(cfg)),
        "rows": rows,
    })  # fmt: skip
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
