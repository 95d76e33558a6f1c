"""Ablation of the mean start: U4D with the training mean image as x0 in stage 2 only (stage 1 samples as before).

    python benchmarks/diagnostics/diag_mean_start.py --below -10 --data-root data/sim_seg \
        --out runs/meanstart/u4d_ms_s2 --num 16

The mean start itself is `u4d generate ... mean_start_below=-10` (both stages; `sampling.mean_start`,
`pipeline.MeanStart`); this script wraps only the conditional (stage-2) sampler calls, by patching
`u4d_aug.pipeline.sample_named`, to separate what each stage's first step costs
(benchmarks/results/generation/mean_start_diagnostic.md). Samples are seeded from 5000 like that table's other rows.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import torch

import u4d_aug.pipeline as pipeline
from u4d_aug import cli
from u4d_aug.batches import row_mean
from u4d_aug.sampling import mean_start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--below", type=float, required=True, help="log-SNR under which stage 2's x0 is the mean")
    parser.add_argument("--data-root", default="data/sim_seg", help="the U4D net's training scans")
    parser.add_argument("--num", type=int, default=16)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = pipeline.load_generator("weights/u4d.pt").config  # the one net of generate_hdl64.yaml, both stages
    mean = row_mean(dataclasses.replace(cfg, data_root=args.data_root), "x0")  # (2, H, 1): its stage-2 target
    original = pipeline.sample_named

    def patched(name, denoise, shape, steps, generator, **kw):
        if kw.get("cond") is not None:  # stage 2; stage 1 is unconditional and keeps its own x0
            denoise = mean_start(denoise, mean, args.below)
        return original(name, denoise, shape, steps, generator, **kw)

    pipeline.sample_named = patched
    argv = ["generate", "configs/u4d/generate_hdl64.yaml", "--out", args.out, "mode=u4d", "mean_start_below=null"]
    return cli.main([*argv, f"num={args.num}", "seed=5000", "--no-progress"])


if __name__ == "__main__":
    sys.exit(main())
