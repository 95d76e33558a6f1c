"""Multiply-add count of a seg-train preset's net per convolution, on the batches its training loop draws.

    python benchmarks/bench_seg_flops.py                       # cpu_minkunet preset, first 2 batches
    python benchmarks/bench_seg_flops.py --variant "" --variant "model.decoder_channels=[256,128,96,64]"

Every sparse convolution's cost is its kernel-map pairs x C_in x C_out x 2 FLOP (gather-GEMM-scatter does exactly
these products; the identity offset of a submanifold conv counts its M rows). Convolutions with the same
(output voxels, C_in, C_out, kernel volume) are summed into one row; kernel-1 products, norms and the head are
left out (< 1 % here). Backward costs about twice the forward. Writes benchmarks/results/segmentation/seg_flops.json.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch

import segmentation.sparse as sparse
from segmentation.batches import TrainBatches, train_scans
from segmentation.config import SegTrainConfig
from segmentation.models import build_model
from u4d_aug.config import load_config
from u4d_aug.distributed import DistInfo
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[1]
CPU = DistInfo(0, 1, 0, torch.device("cpu"))


@contextmanager
def counting_convs(table: dict):
    """Within the block, every `sparse.sparse_conv` call adds its FLOP to table[(M_out, C_in, C_out, K)]."""
    original = sparse.sparse_conv

    def counted(
        features: torch.Tensor, weight: torch.Tensor, kmap: sparse.KernelMap, keep_gathers: bool = False
    ) -> torch.Tensor:
        volume, c_in, c_out = weight.shape
        table[(kmap.num_out, c_in, c_out, volume)] += 2.0 * kmap.num_pairs() * c_in * c_out
        return original(features, weight, kmap, keep_gathers)

    sparse.sparse_conv = counted
    try:
        yield
    finally:
        sparse.sparse_conv = original


def forward_flops(cfg: SegTrainConfig, batches: int) -> dict:
    """Mean forward GFLOP per training batch and the per-conv rows of the first batch."""
    loader = TrainBatches(train_scans(cfg, CPU), cfg, 0, 1)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model).eval()
    totals, first = [], None
    for step in range(batches):
        table: dict = defaultdict(float)
        with torch.no_grad(), counting_convs(table):
            model(loader[step]["points"])
        totals.append(sum(table.values()) / 1e9)
        first = first if first is not None else table
    total = sum(first.values())
    rows = [
        {"voxels_out": m, "c_in": ci, "c_out": co, "kernel_volume": k, "gflop": f / 1e9, "share": f / total}
        for (m, ci, co, k), f in sorted(first.items(), key=lambda kv: -kv[1])
    ]
    return {"forward_gflop_per_batch": sum(totals) / len(totals), "batches": batches, "convs_of_batch_0": rows}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=REPO / "configs" / "seg" / "cpu_minkunet.yaml")
    parser.add_argument("--variant", action="append", help='space-separated key=value overrides ("" = the preset)')
    parser.add_argument("--batches", type=int, default=2, help="training batches counted (their mean is reported)")
    parser.add_argument("--rows", type=int, default=8, help="heaviest conv rows printed per variant")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "seg_flops.json")
    args = parser.parse_args()
    variants = args.variant if args.variant is not None else [""]
    results = []
    for text in variants:
        try:
            cfg = load_config(SegTrainConfig, args.config, shlex.split(text))
            result = {"variant": text or "(preset)", **forward_flops(cfg, args.batches)}
        except InputError as err:  # a bad override, a missing data root or no labelled scan
            print(f"error: {err}", file=sys.stderr)
            return 2
        results.append(result)
        print(
            f"\n{result['variant']}: {result['forward_gflop_per_batch']:.2f} GFLOP per forward (batch as in the preset)"
        )
        print(f"{'voxels out':>10} {'C_in':>5} {'C_out':>5} {'K':>3} {'GFLOP':>7} {'share':>6}")
        for row in result["convs_of_batch_0"][: args.rows]:
            print(
                f"{row['voxels_out']:10d} {row['c_in']:5d} {row['c_out']:5d} {row['kernel_volume']:3d} "
                f"{row['gflop']:7.3f} {row['share'] * 100:5.1f}%"
            )
    atomic_write_json(
        args.out,
        {
            "command": "python benchmarks/bench_seg_flops.py " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
            "config": str(args.config),
            "variants": results,
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
