"""ECE and reliability of any segmentor's saved per-point probabilities against SemanticKITTI labels.

    python examples/ece_of_saved_probabilities.py PROBS DATA [--bins 10] [--png reliability.png] [--json]

PROBS holds one (N, K) array of softmax probabilities per scan, `PROBS/sequences/XX/probs/NNNNNN.npy` (the
layout `u4d seg-predict` writes; any model's outputs saved so work), rows in the order of the points of
`DATA/sequences/XX/velodyne/NNNNNN.bin`; DATA holds the labels, `DATA/sequences/XX/labels/NNNNNN.label`. Points
labelled ignore (19) are left out. Prints the ECE per scan (mean over scans, as Calib3D reports it), the ECE with
every point in one pool of bins, accuracy and mean confidence, and the reliability bins; `--png` draws them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from segmentation import CalibrationAccumulator, plot_reliability
from u4d_aug import SEMANTICKITTI_IGNORE, load_probs, map_semantickitti, read_kitti_label


def main(argv: list[str] | None = None) -> int:
    """Accumulate the calibration of every scan that has both probabilities and labels; print the summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("probs", type=Path, help="PROBS/sequences/XX/probs/NNNNNN.npy, (N, K) probabilities")
    parser.add_argument("data", type=Path, help="DATA/sequences/XX/labels/NNNNNN.label, SemanticKITTI labels")
    parser.add_argument("--bins", type=int, default=10, help="equal-width confidence bins")
    parser.add_argument("--png", type=Path, default=None, help="write the reliability diagram here")
    parser.add_argument("--json", action="store_true", help="print json instead of a table")
    args = parser.parse_args(argv)

    calibration = CalibrationAccumulator(ignore_index=SEMANTICKITTI_IGNORE, num_bins=args.bins)
    for path in sorted(args.probs.glob("sequences/*/probs/*.npy")):
        seq, frame = path.parent.parent.name, path.stem
        label_path = args.data / "sequences" / seq / "labels" / f"{frame}.label"
        if not label_path.is_file():
            continue
        semantic, _ = read_kitti_label(label_path)
        calibration.update(load_probs(path, num_points=len(semantic)), map_semantickitti(semantic))
    if not calibration.scan_eces:
        parser.error(f"no scan of {args.probs} has labels under {args.data}")

    bins = calibration.pooled
    summary = {
        "scans": len(calibration.scan_eces),
        "ece_per_scan": calibration.ece_per_scan,
        "ece_pooled": calibration.ece_pooled,
        "accuracy": float(bins.correct_sum.sum() / max(bins.count.sum(), 1)),
        "confidence": float(bins.confidence_sum.sum() / max(bins.count.sum(), 1)),
        "bins": bins.to_dict(),
    }
    if args.png is not None:
        plot_reliability(bins, args.png, title=f"{summary['scans']} scans, ECE {100 * summary['ece_pooled']:.1f} %")
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"scans {summary['scans']}: ECE per scan {100 * summary['ece_per_scan']:.2f} %, pooled "
          f"{100 * summary['ece_pooled']:.2f} %, accuracy {100 * summary['accuracy']:.1f} %, "
          f"mean confidence {100 * summary['confidence']:.1f} %")  # fmt: skip
    print("confidence bin     points  accuracy  confidence")
    edges = np.asarray(summary["bins"]["edges"])
    for m in range(bins.num_bins):
        if bins.count[m]:
            print(f"({edges[m]:.1f}, {edges[m + 1]:.1f}]  {bins.count[m]:>10d}  {bins.accuracy[m]:8.3f}  "
                  f"{bins.confidence[m]:10.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
