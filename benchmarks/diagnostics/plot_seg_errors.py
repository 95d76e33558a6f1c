"""Where a segmentor goes wrong on one scan: BEV of the ground truth, the prediction and the wrong points.

    python benchmarks/diagnostics/plot_seg_errors.py runs/lean_v025_s0/model.pt data/sim_seg --sequence 95 --frame 3 \
        --out benchmarks/results/segmentation/seg_cpu_rich/lean_voxel025_errors_95_3.png

Three bird's-eye views of the scan (SemanticKITTI palette): labels, predicted classes, and the wrongly predicted
points coloured by the predicted class (right points grey). --focus CLASS centres a fourth, zoomed view on the
points predicted as CLASS that are not CLASS. Prints the scan's point count per (ground truth -> prediction) pair
for the 8 largest errors.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from segmentation.predict import load_checkpoint, model_from_checkpoint, predict_probs  # noqa: E402
from u4d_aug.data.datasets import ScanDataset  # noqa: E402
from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, SEMANTICKITTI_IGNORE  # noqa: E402
from u4d_aug.errors import InputError, exit_code_of  # noqa: E402
from u4d_aug.viz import draw_bev, label_colors, save_figure  # noqa: E402


def run(argv: list[str] | None = None) -> int:
    """Parse the arguments, predict the scan, print its largest errors and draw the figure."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("data", type=Path)
    parser.add_argument("--sequence", required=True)
    parser.add_argument("--frame", type=int, required=True, help="index of the labelled scan in the sequence")
    parser.add_argument("--focus", default="truck", help="class whose false positives the zoomed view centres on")
    parser.add_argument("--extent", type=float, default=50.0, help="half width of the BEV views (m)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    names = list(SEMANTICKITTI_CLASSES)
    if args.focus not in names:
        raise InputError(f"--focus: unknown class {args.focus!r}; valid: {names}")
    dataset = ScanDataset(args.data, [args.sequence], labeled_only=True)
    if not 0 <= args.frame < len(dataset):
        raise InputError(
            f"--frame {args.frame}: sequence {args.sequence} of {args.data} has {len(dataset)} labelled scans"
        )
    item = dataset[args.frame]
    model = model_from_checkpoint(load_checkpoint(args.checkpoint), torch.device("cpu"), str(args.checkpoint)).eval()
    points, target = item["points"], item["labels"]  # (N, 4), (N,)
    pred = predict_probs(model, points, torch.device("cpu")).argmax(1).numpy()
    valid = target != SEMANTICKITTI_IGNORE
    wrong = valid & (pred != target)
    pairs, counts = np.unique(np.stack([target[wrong], pred[wrong]]), axis=1, return_counts=True)
    print(f"{args.sequence}/{args.frame}: {int(wrong.sum())} of {int(valid.sum())} labelled points wrong")
    for k in np.argsort(-counts)[:8]:
        print(f"  {names[pairs[0, k]]:>14} -> {names[pairs[1, k]]:<14} {counts[k]:7d}")

    focus = names.index(args.focus)
    false_pos = valid & (pred == focus) & (target != focus)
    panels = 4 if false_pos.any() else 3
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 5.4))
    draw_bev(axes[0], points, label_colors(np.where(valid, target, 19)), args.extent, "ground truth", 0.3)
    draw_bev(axes[1], points, label_colors(pred), args.extent, "prediction", 0.3)
    error_colors = np.full((len(points), 3), 0.35)
    error_colors[wrong] = label_colors(pred[wrong])
    draw_bev(axes[2], points, error_colors, args.extent, "wrong points, coloured by prediction", 0.3)
    if false_pos.any():
        centre = points[false_pos, :2].mean(axis=0)
        near = np.abs(points[:, :2] - centre).max(axis=1) < 12.0
        local = points[near].copy()
        local[:, :2] -= centre
        draw_bev(axes[3], local, label_colors(np.where(valid, target, 19))[near], 12.0, "", 2.0)
        fp_local = false_pos[near]
        axes[3].scatter(local[fp_local, 0], local[fp_local, 1], s=2.0, c="white", linewidths=0)
        axes[3].set_title(
            f"ground truth around the {int(false_pos.sum())} points taken for {args.focus} (white)", fontsize=9
        )
    fig.suptitle(f"{args.checkpoint} on {args.data} sequence {args.sequence}, scan {args.frame}", fontsize=10)
    save_figure(fig, args.out)
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with bad input (unknown class, missing checkpoint or data, no labelled scan) as a one-line error."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
