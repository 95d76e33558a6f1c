"""Diagnostic: the sampler's first steps with the training data's per-row mean image as the x0 estimate.

    python benchmarks/diag_mean_start.py --mode baseline --below -10 --out runs/meanstart/baseline --num 16
    python benchmarks/diag_mean_start.py --mode u4d --below -10 --stage1 --out runs/meanstart/u4d --num 16
    u4d evaluate --bank runs/meanstart/baseline --real data/sim_seg --real-sequences 88-99 \
        --metrics jsd,mmd,points,rangejs,intensityjs --json --out runs/meanstart/eval_baseline

At the first step (log-SNR -15) an eps-parametrised net's data estimate x0 = (x_t - sigma eps)/alpha divides by
alpha = 5e-4: it is clamped noise whose mean sits at the encoding's 0 (intensity 0.5, mid range), and the samplers keep
that low-frequency error. Below `--below` this wraps the denoise function so that it returns the eps of x0 = mu, the
mean of the training range images per row (the MMSE estimate at vanishing SNR), for the baseline and U4D stage 2 (mu
of the full scans) and, with --stage1, U4D stage 1 (mu of the x0_u images). A diagnostic: it wraps the denoise
function with `u4d_aug.sampling.mean_start` by patching `u4d_aug.pipeline.sample_named`, then runs
`u4d generate configs/u4d/generate_hdl64.yaml` (samples seeded from 5000); without --below it is plain `u4d generate`.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import torch

import u4d_aug.pipeline as pipeline
from u4d_aug import cli
from u4d_aug.batches import RangeImages
from u4d_aug.sampling import mean_start


def row_mean(net_path: str, data_root: str, probs_root: str, key: str, count: int = 32) -> torch.Tensor:
    """(C, H, 1) mean over `count` evenly spaced training scans (places 00-87) of their `key` image (x0 or x0_u)."""
    cfg = pipeline.load_generator(net_path)[1]
    cfg = dataclasses.replace(cfg, data_root=data_root, probs_root=probs_root, sequences=["00-87"])
    images = RangeImages(cfg)
    step = max(1, len(images) // count)
    return torch.stack([images[i][key] for i in range(0, len(images), step)][:count]).mean(dim=(0, 3), keepdim=True)[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=["baseline", "u4d"], default="baseline")
    parser.add_argument("--below", type=float, default=None, help="log-SNR under which x0 = mu (none: plain sampling)")
    parser.add_argument("--stage1", action="store_true", help="also U4D stage 1, with the mean of the x0_u images")
    parser.add_argument("--data-root", default="data/sim_seg")
    parser.add_argument("--probs-root", default="data/sim_seg_probs")
    parser.add_argument("--num", type=int, default=16)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    mu = row_mean("weights/baseline.pt", args.data_root, args.probs_root, "x0")  # (2, 64, 1)
    mu_u = row_mean("weights/u4d_stage1.pt", args.data_root, args.probs_root, "x0_u") if args.stage1 else None
    original = pipeline.sample_named

    def patched(name, denoise, shape, steps, generator, **kw):
        # the baseline and stage 2 (conditional) start from the scans' mean, stage 1 (u4d, unconditional) from x0_u's
        target = mu if args.mode == "baseline" or kw.get("cond") is not None else mu_u
        if args.below is not None and target is not None:
            denoise = mean_start(denoise, target, args.below)
        return original(name, denoise, shape, steps, generator, **kw)

    pipeline.sample_named = patched
    argv = ["generate", "configs/u4d/generate_hdl64.yaml", "--out", args.out, f"mode={args.mode}"]
    return cli.main([*argv, f"num={args.num}", "seed=5000", "--no-progress"])


if __name__ == "__main__":
    sys.exit(main())
