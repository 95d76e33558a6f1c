"""Training-step time of a seg-train preset under config variants, measured side by side in one process.

    python benchmarks/bench_seg_step.py                      # cpu_minkunet preset: loss on points vs on voxels
    python benchmarks/bench_seg_step.py --steps 4 --threads 1
    python benchmarks/bench_seg_step.py --variant "" --variant "loss.level=voxel data.max_points=30000"
    python benchmarks/bench_seg_step.py --steps 2 --threads 1 --variant "" --profile   # where a step's time goes

Every variant gets its own net (same seed, so the same initial weights), its own AdamW and the batches the
training loop would draw (`segmentation.batches.TrainBatches`: the preset's scans, point subsets and
augmentation, step for step). The steps interleave - variant A step s, variant B step s, ... - so that load
changes on the machine hit every variant alike; one warm-up step each, then the median over --steps timed
steps of the whole `supervised_step` + backward + optimiser step. Also reports how many rows the losses read
per step (points, or voxels with loss.level=voxel) and the memory autograd keeps for backward in the warm-up step
(the storages of the saved tensors, counted once; `model.keep_gathers` adds the convolutions' gathered inputs).
Writes benchmarks/results/segmentation/seg_step.json.

--profile: the timed steps run under torch.profiler; per variant the operators with the most self time (share of
the profiled time) and the rate of the matrix products (aten::mm FLOPs / its self time) against the profiled
steps, which tells whether a step is bound by arithmetic (fewer FLOPs help) or by gathers and scatters. The step
times of a --profile run include the profiler's overhead: compare variants within it, not with runs without it.
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from segmentation.batches import TrainBatches, train_class_counts, train_scans
from segmentation.config import SegTrainConfig
from segmentation.losses import class_weights
from segmentation.models import build_model
from segmentation.optimizer import make_optimizer
from segmentation.sparse import voxelize
from segmentation.train import supervised_step
from u4d_aug.config import load_config
from u4d_aug.distributed import DistInfo
from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[1]
CPU = DistInfo(0, 1, 0, torch.device("cpu"))


def loss_rows(cfg: SegTrainConfig, batch: dict) -> int:
    """Rows the training losses read in this batch: points, or occupied voxels with loss.level=voxel."""
    if cfg.loss.level == "point":
        return sum(int(p.shape[0]) for p in batch["points"])
    return voxelize(list(batch["points"]), cfg.model.voxel_size)[0].num_voxels


def set_up(config: Path, variants: list[str]) -> list[dict]:
    """Per variant: its config, batches, net (seeded, the same initial weights), AdamW and class weights."""
    runs = []
    for text in variants:
        cfg = load_config(SegTrainConfig, config, shlex.split(text))
        scans = train_scans(cfg, CPU)
        weight = class_weights(train_class_counts(scans), cfg.loss) if cfg.loss.class_weighting != "none" else None
        torch.manual_seed(cfg.seed)
        model = build_model(cfg.model).train()
        runs.append(
            {
                "variant": text or "(preset)",
                "cfg": cfg,
                "batches": TrainBatches(scans, cfg, 0, 1),
                "model": model,
                "optimizer": make_optimizer(model, cfg.optim),
                "weight": weight,
                "times": [],
                "rows": [],
            }
        )
    return runs


class SavedBytes:
    """Bytes autograd holds for backward during a forward: the storages of the saved tensors, each counted once."""

    def __init__(self) -> None:
        self.storages: dict[int, int] = {}

    def pack(self, tensor: torch.Tensor) -> torch.Tensor:
        for part in storage_parts(tensor):
            storage = part.untyped_storage()
            self.storages[storage.data_ptr()] = storage.nbytes()
        return tensor

    @property
    def megabytes(self) -> float:
        return sum(self.storages.values()) / 2**20


def storage_parts(tensor: torch.Tensor) -> list[torch.Tensor]:
    """The dense tensors holding a tensor's data: itself, or a sparse one's indices and values (CSR / COO)."""
    if tensor.layout == torch.sparse_csr:
        return [tensor.crow_indices(), tensor.col_indices(), tensor.values()]
    elif tensor.layout == torch.sparse_coo:
        return [tensor._indices(), tensor._values()]
    return [tensor]


def add_profile(ops: dict, profiler: profile) -> None:
    """Accumulate self CPU seconds, calls and FLOPs per operator name from one profiled step into `ops`."""
    for event in profiler.key_averages():
        entry = ops.setdefault(event.key, {"self_seconds": 0.0, "calls": 0, "flops": 0})
        entry["self_seconds"] += event.self_cpu_time_total / 1e6
        entry["calls"] += event.count
        entry["flops"] += event.flops or 0


def profile_summary(ops: dict, top: int = 12) -> dict:
    """The `top` operators by self time (seconds, share, calls) and the rate of aten::mm over the profiled steps."""
    total = sum(entry["self_seconds"] for entry in ops.values())
    ranked = sorted(ops.items(), key=lambda item: -item[1]["self_seconds"])[:top]
    mm = ops.get("aten::mm", {"self_seconds": 0.0, "flops": 0})
    return {
        "profiled_seconds": total,
        "mm_gflop_per_second": mm["flops"] / mm["self_seconds"] / 1e9 if mm["self_seconds"] else 0.0,
        "top_ops": [
            {"op": name, "self_seconds": e["self_seconds"], "share": e["self_seconds"] / total, "calls": e["calls"]}
            for name, e in ranked
        ],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=REPO / "configs" / "seg" / "cpu_minkunet.yaml")
    parser.add_argument(
        "--variant",
        action="append",
        help='space-separated key=value overrides of one variant ("" = the preset); default: point vs voxel loss',
    )
    parser.add_argument("--steps", type=int, default=6, help="timed steps per variant (after one warm-up step)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "seg_step.json")
    parser.add_argument("--profile", action="store_true", help="operator breakdown of the timed steps (torch.profiler)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    variants = args.variant if args.variant is not None else ["loss.level=point", "loss.level=voxel"]

    try:
        runs = set_up(args.config, variants)
    except InputError as err:  # a bad override, a missing data root or no labelled scan
        print(f"error: {err}", file=sys.stderr)
        return 2
    for step in range(args.steps + 1):
        for run in runs:
            batch = run["batches"][step]
            profiler = profile(activities=[ProfilerActivity.CPU], with_flops=True) if args.profile and step else None
            saved = SavedBytes() if step == 0 else None  # the warm-up step counts what backward keeps
            hooks = torch.autograd.graph.saved_tensors_hooks(saved.pack, lambda t: t) if saved else None
            with profiler or contextlib.nullcontext():
                start = time.perf_counter()
                with hooks or contextlib.nullcontext():
                    losses = supervised_step(run["model"], batch, run["cfg"], torch.device("cpu"), run["weight"])
                run["optimizer"].zero_grad(set_to_none=True)
                losses["loss"].backward()
                run["optimizer"].step()
                seconds = time.perf_counter() - start
            if saved is not None:
                run["saved_mb"] = saved.megabytes
            if step:
                run["times"].append(seconds)
                run["rows"].append(loss_rows(run["cfg"], batch))
            if profiler is not None:
                add_profile(run.setdefault("ops", {}), profiler)
        print(f"step {step}/{args.steps}", file=sys.stderr, flush=True)

    base = statistics.median(runs[0]["times"])
    rows = []
    for run in runs:
        median = statistics.median(run["times"])
        rows.append(
            {
                "variant": run["variant"],
                "step_seconds": median,
                "steps_per_second": 1.0 / median,
                "speedup_vs_first": base / median,
                "loss_rows_per_step": statistics.median(run["rows"]),
                "saved_for_backward_mb": run["saved_mb"],
                "step_times": run["times"],
            }
        )
        if "ops" in run:
            rows[-1]["profile"] = profile_summary(run["ops"])
    print(f"\n{args.config.name}, {args.threads} thread(s), median of {args.steps} steps (batch as in the preset)")
    print(f"{'variant':<48} {'s/step':>7} {'steps/s':>8} {'speed-up':>8} {'loss rows':>10} {'saved MB':>9}")
    for row in rows:
        print(
            f"{row['variant']:<48} {row['step_seconds']:7.3f} {row['steps_per_second']:8.3f} "
            f"{row['speedup_vs_first']:7.2f}x {row['loss_rows_per_step']:10.0f} {row['saved_for_backward_mb']:9.0f}"
        )
    atomic_write_json(
        args.out,
        {
            "command": "python benchmarks/bench_seg_step.py " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
            "config": str(args.config),
            "threads": args.threads,
            "steps": args.steps,
            "machine": host_info(),
            "rows": rows,
        },
    )
    for row in rows:
        if "profile" in row:
            prof = row["profile"]
            print(
                f"\n{row['variant']}: {prof['profiled_seconds']:.2f} s profiled, matrix products at "
                f"{prof['mm_gflop_per_second']:.1f} GFLOP/s"
            )
            for op in prof["top_ops"]:
                print(f"  {op['op']:<40} {op['self_seconds']:7.3f} s {100 * op['share']:5.1f} % {op['calls']:7d} calls")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
