"""Can re-weighting a class fix it? Post-hoc logit adjustment of a trained segmentor, class by class.

    python benchmarks/diagnostics/bench_logit_bias.py runs/lean_v025_s0/model.pt data/sim_seg --sequences 88-99 \
        --every 2 --classes other-ground parking truck terrain

Class-weighted cross-entropy shifts a net's logits by roughly log w_c (Menon et al., "Long-tail learning via logit
adjustment", ICLR 2021). Adding a bias b to class c's log-probability after training shows what such a shift can
buy with the features the net has: if no b lifts IoU_c without costing the classes c is mistaken for as much, the
net does not tell c apart and a class weight will not either (more training or context must). Per class of
--classes and bias in --biases: mIoU, IoU_c and the IoU of the two classes c is most mistaken for. Scans: every
--every-th labelled scan of --sequences, one forward each (log-probabilities kept in float16). Writes
benchmarks/results/segmentation/logit_bias.json.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from segmentation.metrics import ConfusionMatrix, iou_per_class, top_confusions
from segmentation.predict import load_checkpoint, model_from_checkpoint, parse_sequences, predict_probs
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, SEMANTICKITTI_IGNORE
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[2]


def collect(checkpoint: Path, root: Path, sequences: list[str] | None, every: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, K) float16 log-probabilities and (N,) train-id targets of every `every`-th labelled scan."""
    model = model_from_checkpoint(load_checkpoint(checkpoint), torch.device("cpu"), str(checkpoint)).eval()
    dataset = ScanDataset(root, sequences, labeled_only=True)
    if len(dataset) == 0:
        raise InputError(f"{root}: no labelled scan in sequences {dataset.sequences}")
    log_probs, targets = [], []
    for index in tqdm(range(0, len(dataset), every), desc="scans"):
        item = dataset[index]
        probs = predict_probs(model, item["points"], torch.device("cpu"))  # (N, K)
        log_probs.append(probs.clamp_min(1e-12).log().half())
        targets.append(torch.from_numpy(item["labels"]))
    return torch.cat(log_probs), torch.cat(targets)


def iou_with_bias(log_probs: torch.Tensor, target: torch.Tensor, bias: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(K,) IoU and (K, K) confusion of argmax(log_probs + bias) (K,) against target; the ignore id left out."""
    cm = ConfusionMatrix(log_probs.shape[1], SEMANTICKITTI_IGNORE)
    for start in range(0, len(target), 1 << 20):  # float32 in chunks: the float16 tensor stays the big one
        part = log_probs[start : start + (1 << 20)].float() + bias
        cm.update(part.argmax(dim=1), target[start : start + (1 << 20)])
    return iou_per_class(cm.matrix), cm.matrix


def run(argv: list[str] | None = None) -> int:
    """Parse the arguments, measure, print the table and write the json."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("data", type=Path)
    parser.add_argument("--sequences", nargs="+", default=None)
    parser.add_argument("--every", type=int, default=2, help="every n-th labelled scan")
    parser.add_argument("--classes", nargs="+", default=["other-ground", "parking", "truck", "terrain"])
    parser.add_argument("--biases", type=float, nargs="+", default=[-1.0, 1.0, 2.0, 3.0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "logit_bias.json"
    )
    args = parser.parse_args(argv)
    names = list(SEMANTICKITTI_CLASSES)
    unknown = [c for c in args.classes if c not in names]
    if unknown:
        raise InputError(f"--classes: unknown class names {unknown}; valid: {names}")
    if args.every < 1:
        raise InputError(f"--every must be >= 1, got {args.every}")
    torch.set_num_threads(args.threads)
    log_probs, target = collect(args.checkpoint, args.data, parse_sequences(args.sequences), args.every)
    k = log_probs.shape[1]
    base_iou, base_cm = iou_with_bias(log_probs, target, torch.zeros(k))
    confused = top_confusions(base_cm)
    rows = []
    print(f"\nno bias: mIoU {100 * np.nanmean(base_iou):.2f} % on {len(target)} points")
    print(f"{'class':<13} {'bias':>5} {'mIoU':>6} {'IoU_c':>6}  IoU of the classes c is mistaken for")
    for name in args.classes:
        c = names.index(name)
        partners = [p for p, _ in confused[c]]
        for bias in [0.0, *args.biases]:
            shift = torch.zeros(k)
            shift[c] = bias
            iou, _ = iou_with_bias(log_probs, target, shift) if bias else (base_iou, base_cm)
            row = {
                "class": name,
                "bias": bias,
                "miou": float(np.nanmean(iou)),
                "iou": float(iou[c]),
                "partners": {names[p]: float(iou[p]) for p in partners},
            }
            rows.append(row)
            partner_text = ", ".join(f"{p} {100 * v:.1f}" for p, v in row["partners"].items())
            print(f"{name:<13} {bias:5.1f} {100 * row['miou']:6.2f} {100 * row['iou']:6.1f}  {partner_text}")
    atomic_write_json(
        args.out,
        {
            "command": "python benchmarks/diagnostics/bench_logit_bias.py "
            + " ".join(shlex.quote(a) for a in sys.argv[1:]),
            "machine": host_info(),
            "points": int(len(target)),
            "base_iou": {n: (None if np.isnan(v) else float(v)) for n, v in zip(names, base_iou)},
            "mistaken_for": {names[c]: {names[p]: s for p, s in confused[c]} for c in range(k)},
            "rows": rows,
        },
    )
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with bad input (unknown class, missing checkpoint or data, no labelled scan) as a one-line error."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
