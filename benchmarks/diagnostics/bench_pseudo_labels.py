"""Pseudo-label quality of a mean teacher: kept share and accuracy per threshold and per class, on scans whose
labels the teacher never saw (the unlabeled part of the split; the simulated world labels every scan).

The teacher of a mode-"semi" training checkpoint (`ema` weights) pseudo-labels `--scans` scans of the unlabeled
split in batches of optim.batch_size, as in training (BatchNorm in the bn_mode of the run, training subsample of
data.max_points points, no augmentation). For each global threshold: the share of labelled points kept and the
accuracy of the kept pseudo-labels; then per class, the global threshold (semi.pseudo_threshold) against
class-balanced pseudo-labels (semi.pseudo_class_share, `--class-shares`): the share of each ground-truth class
that gets a pseudo-label, each class's share of all pseudo-labels and their precision.

    python benchmarks/diagnostics/bench_pseudo_labels.py RUN/checkpoints/step_0000600.pt \
        [--scans 8] [--class-shares 0.2 0.5]

Writes benchmarks/results/segmentation/pseudo_labels.json (or --out).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

from segmentation.config import SegTrainConfig
from segmentation.mean_teacher import pseudo_labels, teacher_mode
from segmentation.models import build_model
from segmentation.semi import unlabeled_stream
from u4d_aug.config import saved_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, SEMANTICKITTI_IGNORE
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json, load_checkpoint

REPO = Path(__file__).resolve().parents[2]
THRESHOLDS = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


def teacher_outputs(ckpt_path: Path, num_scans: int, seed: int) -> tuple[SegTrainConfig, int, list, list]:
    """(run config, step, teacher logits (sum N, K) per batch, ground truth (sum N,) per batch)."""
    if not ckpt_path.is_file():
        raise InputError(f"{ckpt_path}: checkpoint not found (expected RUN/checkpoints/step_*.pt of a mode 'semi' run)")
    ckpt = load_checkpoint(ckpt_path, "seg-train checkpoint")
    if ckpt.get("ema") is None:
        raise InputError(f"{ckpt_path}: no teacher (ema) weights; pass a checkpoint of a mode 'semi' run")
    cfg = saved_config(SegTrainConfig, ckpt["config"], str(ckpt_path))
    teacher = build_model(cfg.model)
    teacher.load_state_dict(ckpt["ema"])
    teacher_mode(teacher, cfg.semi.bn_mode)
    split = unlabeled_stream(cfg).sources[0]  # the unlabeled part of the label split
    labelled = ScanDataset(cfg.data.root, cfg.data.train_sequences, labeled_only=True)
    has_labels = set(labelled.entries)
    labelled.entries = [entry for entry in split.entries if entry in has_labels]
    if len(labelled) == 0:
        raise InputError(f"{cfg.data.root}: the unlabeled split has no label files to score pseudo-labels against")
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(labelled), min(num_scans, len(labelled)), replace=False).tolist()
    logits, truth = [], []
    batch = cfg.optim.batch_size
    with torch.no_grad():
        for start in range(0, len(picks), batch):
            scans, labels = [], []
            for index in picks[start : start + batch]:
                item = labelled[index]
                points, target = item["points"], item["labels"]
                if cfg.data.max_points is not None and len(points) > cfg.data.max_points:
                    keep = rng.choice(len(points), cfg.data.max_points, replace=False)
                    points, target = points[keep], target[keep]
                scans.append(torch.from_numpy(np.ascontiguousarray(points)))
                labels.append(torch.from_numpy(np.ascontiguousarray(target)).long())
            logits.append(teacher(scans).float())
            truth.append(torch.cat(labels))
    return cfg, int(ckpt["step"]), logits, truth


def pct(value: float | None) -> str:
    return "  - " if value is None else f"{100 * value:4.0f}"


def per_class_rows(pseudo: torch.Tensor, truth: torch.Tensor) -> list[dict]:
    """Per class: share of its ground-truth points kept, its share of the pseudo-labels, their precision."""
    kept = pseudo != SEMANTICKITTI_IGNORE
    rows = []
    for k, name in enumerate(SEMANTICKITTI_CLASSES):
        in_class, labelled_as = truth == k, kept & (pseudo == k)
        rows.append({
            "class": name,
            "gt_share": float(in_class.float().mean()),
            "kept_of_class": float(kept[in_class].float().mean()) if in_class.any() else None,
            "pseudo_share": float(labelled_as.sum() / kept.sum().clamp_min(1)),
            "precision": float((truth[labelled_as] == k).float().mean()) if labelled_as.any() else None,
        })  # fmt: skip
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="a mode-'semi' training checkpoint (RUN/checkpoints/step_*.pt)")
    parser.add_argument("--scans", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0, help="which unlabeled scans and subsamples")
    parser.add_argument("--class-shares", type=float, nargs="*", default=[0.2, 0.5])
    parser.add_argument(
        "--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "pseudo_labels.json"
    )
    args = parser.parse_args()
    try:
        cfg, step, logits, truth = teacher_outputs(args.checkpoint, args.scans, args.seed)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    valid = [t != SEMANTICKITTI_IGNORE for t in truth]
    confidence = torch.cat([torch.softmax(z, 1).max(1).values[v] for z, v in zip(logits, valid)])
    correct = torch.cat([(z.argmax(1) == t)[v] for z, t, v in zip(logits, truth, valid)]).float()
    print(f"{args.checkpoint} (step {step}): {len(correct)} labelled points of {args.scans} unlabeled-split scans")
    print(f"teacher accuracy {100 * float(correct.mean()):.1f} %")
    print(f"{'threshold':>9} {'kept %':>7} {'accuracy %':>10}")
    global_rows = []
    for threshold in THRESHOLDS:
        kept = confidence >= threshold
        accuracy = float(correct[kept].mean()) if kept.any() else math.nan
        global_rows.append({"threshold": threshold, "kept": float(kept.float().mean()), "accuracy": accuracy})
        print(f"{threshold:>9.2f} {100 * float(kept.float().mean()):>7.1f} {100 * accuracy:>10.1f}")

    variants = [("global", None), *[(f"class_share_{s:g}", s) for s in args.class_shares]]
    by_variant = {}
    truth_kept = torch.cat([t[v] for t, v in zip(truth, valid)])
    for name, share in variants:
        threshold = cfg.semi.pseudo_threshold
        pseudo = torch.cat(
            [pseudo_labels(z, threshold, SEMANTICKITTI_IGNORE, share)[0][v] for z, v in zip(logits, valid)]
        )
        kept = pseudo != SEMANTICKITTI_IGNORE
        by_variant[name] = {
            "class_share": share,
            "kept": float(kept.float().mean()),
            "accuracy": float((pseudo[kept] == truth_kept[kept]).float().mean()) if kept.any() else None,
            "classes": per_class_rows(pseudo, truth_kept),
        }
    print(
        f"\nthreshold {cfg.semi.pseudo_threshold}; per class: kept of its points % / share of pseudo-labels % / "
        "precision %"
    )
    print(f"{'class':>14} {'GT %':>6} " + " ".join(f"{name:>24}" for name, _ in variants))
    for k, class_name in enumerate(SEMANTICKITTI_CLASSES):
        cells = []
        for name, _ in variants:
            row = by_variant[name]["classes"][k]
            cells.append(f"{pct(row['kept_of_class'])} / {100 * row['pseudo_share']:5.1f} / {pct(row['precision'])}")
        print(
            f"{class_name:>14} {100 * by_variant['global']['classes'][k]['gt_share']:>6.2f} "
            + " ".join(f"{c:>24}" for c in cells)
        )
    print(
        "all: "
        + ", ".join(
            f"{n} kept {100 * v['kept']:.1f} % at {100 * (v['accuracy'] or 0):.1f} %" for n, v in by_variant.items()
        )
    )
    atomic_write_json(args.out, {
        "command": "python benchmarks/diagnostics/bench_pseudo_labels.py " + " ".join(sys.argv[1:]),
        "checkpoint": str(args.checkpoint),
        "step": step,
        "points": len(correct),
        "teacher_accuracy": float(correct.mean()),
        "thresholds": global_rows,
        "pseudo_threshold": cfg.semi.pseudo_threshold,
        "variants": by_variant,
    })  # fmt: skip
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
