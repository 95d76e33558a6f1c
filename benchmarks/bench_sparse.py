"""Sparse voxel conv (segmentation.sparse) vs dense conv3d on a real KITTI scan; training speed of both nets.

    python benchmarks/bench_sparse.py            # convs at 0.2 / 0.1 m; training at 0.05 m W32 + a CPU preset
    python benchmarks/bench_sparse.py --quick    # fewer repetitions, submanifold conv only, 2 training steps

Conv part: seq 00 scan 000000 (124,668 points) cropped to |x|, |y| < 25.6 m, -3.2 <= z < 3.2 m so that the
dense grid fits in memory (0.2 m: 256 x 256 x 32 cells; 0.1 m: 512 x 512 x 64 cells), voxelised; the voxel
features are random N(0, 1) with C channels (seeded), the same weights for both sides. Cases: submanifold
3x3x3 (dense = conv3d padding 1, read at the occupied voxels), kernel-2 stride-2 (dense = conv3d stride 2) and
transposed kernel-2 stride-2 back onto the voxels (dense = conv_transpose3d). "same result" = max |sparse -
dense| over the occupied outputs. Sparse times are "warm" (kernel map cached, as every block after the first
sees it) and "cold" (map built in the call; none for the transposed conv, which reuses the map of the
downsampling conv that made the coarse level). Dense times exclude filling the grid.

Training part (time-capped by --budget seconds per case, at least one timed step): both nets, batch 2 (frames
0+1, 2+3, 4+5 of the same sequence, full scans, no crop), AdamW and cross-entropy against random labels
(seeded; speed does not depend on label values), steps/s = 1 / median step time after one warm-up step.

Memory: every case runs in its own subprocess. Right before the case (after torch import, scan load,
voxelisation, features/weights or model/data set-up) the kernel's peak-RSS mark is reset (`5` written to
/proc/self/clear_refs); extra memory = VmHWM at the end minus VmRSS at the reset, i.e. the resident memory the
case adds at its peak (incl. the dense grids, kernel maps, autograd buffers). Without /proc it falls back to
`resource.getrusage(RUSAGE_SELF).ru_maxrss` deltas. tracemalloc does not see torch's CPU allocations. Children
run with OMP_WAIT_POLICY=PASSIVE and --threads torch threads (default 2) because spin-waiting OpenMP threads
distort small ops on a shared machine.
Writes benchmarks/results/segmentation/sparse.json. Goal: sparse >= 3x faster than dense with the same result.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from peak_memory import peak_mb, run_case, start_memory_window

from segmentation.models import SegModelConfig, build_model
from segmentation.sparse import SparseConv3d, SparseTensor, voxelize
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json

REPO = Path(__file__).resolve().parents[1]
SEQUENCE = REPO.parent / "shared" / "data" / "real" / "semantickitti" / "sequences" / "00"
CROP_XY, CROP_Z = 25.6, 3.2  # metres; grid origin at (-25.6, -25.6, -3.2)


def load_scan(path: Path) -> torch.Tensor:
    return torch.from_numpy(np.fromfile(path, dtype=np.float32).reshape(-1, 4))


def cropped_voxels(voxel_size: float, channels: int) -> tuple[SparseTensor, tuple[int, int, int]]:
    """Cropped scan 000000 voxelised, random features (C channels), and the dense grid shape."""
    points = load_scan(SEQUENCE / "velodyne" / "000000.bin")
    x, _ = voxelize([points], voxel_size)
    shape = tuple(int(round(2 * e / voxel_size)) for e in (CROP_XY, CROP_XY, CROP_Z))
    shift = torch.tensor([round(-e / voxel_size) for e in (CROP_XY, CROP_XY, CROP_Z)])
    coords = x.coords.clone()
    coords[:, 1:] -= shift  # grid indices from 0; the crop keeps the voxels inside the dense grid
    keep = ((coords[:, 1:] >= 0) & (coords[:, 1:] < torch.tensor(shape))).all(dim=1)
    generator = torch.Generator().manual_seed(0)
    features = torch.randn(int(keep.sum()), channels, generator=generator)
    return SparseTensor(features, coords[keep]), shape


def dense_weight(weight: torch.Tensor, kernel: int, transposed: bool) -> torch.Tensor:
    """(K, C_in, C_out) -> conv3d / conv_transpose3d layout (see segmentation/sparse.py docstring)."""
    w = weight.reshape(kernel, kernel, kernel, weight.shape[1], weight.shape[2])
    return (w.permute(3, 4, 0, 1, 2) if transposed else w.permute(4, 3, 0, 1, 2)).contiguous()


def at_sites(dense: torch.Tensor, coords: torch.Tensor, stride: int) -> torch.Tensor:
    """(1, C, X, Y, Z) dense output read at sparse coords (M, 4) of the given stride -> (M, C)."""
    idx = coords[:, 1:] // stride
    return dense[0, :, idx[:, 0], idx[:, 1], idx[:, 2]].t()


def conv_child(args: argparse.Namespace) -> dict:
    """One conv case in this process: time, peak memory, output at the occupied sites saved for the check."""
    x, shape = cropped_voxels(args.voxel, args.channels)
    c = args.channels
    generator = torch.Generator().manual_seed(1)
    if args.op == "sub":
        conv = SparseConv3d(c, c, 3)
    elif args.op == "down":
        conv = SparseConv3d(c, c, 2, 2)
    else:
        conv = SparseConv3d(c, c, 2, 2, transposed=True)
    with torch.no_grad():
        conv.weight.normal_(generator=generator).mul_(0.05)
    source = x
    if args.op == "up":  # input = coarse level of the same voxels, with random features
        with torch.no_grad():
            coarse = SparseConv3d(c, c, 2, 2)(x)
        source = coarse.replace(torch.randn(coarse.features.shape, generator=generator))
    before = start_memory_window()
    times, cold = [], []
    if args.method == "sparse":
        with torch.no_grad():
            for rep in range(args.reps + 1):
                if args.op != "up":  # fresh cache: the kernel map is built inside the timed call
                    fresh = SparseTensor(source.features, source.coords.clone(), source.stride)
                    start = time.perf_counter()
                    conv(fresh)
                    if rep:
                        cold.append(time.perf_counter() - start)
                start = time.perf_counter()
                out = conv(source)
                if rep:
                    times.append(time.perf_counter() - start)
        result = out.features
        sites = out.coords
    else:
        kernel, transposed = (3, False) if args.op == "sub" else (2, args.op == "up")
        weight = dense_weight(conv.weight.detach(), kernel, transposed)
        grid_shape = shape if args.op != "up" else tuple(s // 2 for s in shape)
        dense_in = source.to_dense(grid_shape)
        with torch.no_grad():
            for rep in range(args.reps):  # no warm-up call: each dense call is seconds long
                start = time.perf_counter()
                if args.op == "sub":
                    dense_out = F.conv3d(dense_in, weight, padding=1)
                elif args.op == "down":
                    dense_out = F.conv3d(dense_in, weight, stride=2)
                else:
                    dense_out = F.conv_transpose3d(dense_in, weight, stride=2)
                times.append(time.perf_counter() - start)
                if rep < args.reps - 1:
                    del dense_out
        with torch.no_grad():
            out_coords = source.coords if args.op == "sub" else conv(source).coords
            stride = 2 if args.op == "down" else 1
        result = at_sites(dense_out, out_coords, stride)
        sites = out_coords
    np.save(args.result, result.numpy())
    return {
        "seconds": statistics.median(times),
        "cold_seconds": statistics.median(cold) if cold else None,
        "peak_extra_mb": peak_mb() - before,
        "peak_total_mb": peak_mb(),
        "voxels_in": source.num_voxels,
        "sites_out": int(sites.shape[0]),
        "grid": list(shape),
    }


def train_child(args: argparse.Namespace) -> dict:
    """Training steps of one net at batch 2 on real scans: steps/s and peak memory."""
    frames = sorted((SEQUENCE / "velodyne").glob("*.bin"))
    scans = [load_scan(path) for path in frames]
    generator = torch.Generator().manual_seed(0)
    labels = [torch.randint(0, 19, (s.shape[0],), generator=generator) for s in scans]
    batches = [(scans[i : i + 2], torch.cat(labels[i : i + 2])) for i in range(0, len(scans) - 1, 2)]
    cfg = SegModelConfig(name=args.net, voxel_size=args.voxel, width=args.width)
    torch.manual_seed(0)
    model = build_model(cfg).train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.01)
    before = start_memory_window()
    times = []
    budget_start = time.perf_counter()
    for step in range(args.steps + 1):
        if step >= 2 and time.perf_counter() - budget_start > args.budget:
            break  # time cap reached after the warm-up and at least one timed step
        batch, target = batches[step % len(batches)]
        start = time.perf_counter()
        loss = F.cross_entropy(model(batch), target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step:
            times.append(time.perf_counter() - start)
    with torch.no_grad():
        voxels = [voxelize(b, cfg.voxel_size)[0].num_voxels for b, _ in batches]
    return {
        "steps_per_second": 1.0 / statistics.median(times),
        "step_seconds": statistics.median(times),
        "timed_steps": len(times),
        "peak_extra_mb": peak_mb() - before,
        "peak_total_mb": peak_mb(),
        "parameters": sum(p.numel() for p in model.parameters()),
        "points_per_batch": [int(t.numel()) for _, t in batches],
        "voxels_per_batch": voxels,
        "loss_last": float(loss.detach()),
    }


def run_child(argv: list[str], threads: int) -> dict:
    return run_case(__file__, ["--threads", str(threads), *argv], " ".join(argv))


def conv_table(args: argparse.Namespace, tmp: Path) -> list[dict]:
    ops = ["sub"] if args.quick else ["sub", "down", "up"]
    rows = []
    for voxel in (0.2, 0.1):
        for op in ops:
            row: dict = {"voxel_size": voxel, "op": op, "channels": args.channels}
            outputs = {}
            for method in ("sparse", "dense"):
                reps = args.reps if method == "sparse" else max(1, args.reps // 2)
                result = tmp / f"{voxel}_{op}_{method}.npy"
                argv = ["--child", "conv", "--method", method, "--op", op, "--voxel", str(voxel)]
                argv += ["--channels", str(args.channels), "--reps", str(reps), "--result", str(result)]
                row[method] = run_child(argv, args.threads)
                outputs[method] = np.load(result)
                print(f"  conv {voxel} m {op} {method}: {row[method]['seconds']:.4f} s", flush=True)
            row["max_abs_diff"] = float(np.abs(outputs["sparse"] - outputs["dense"]).max())
            row["max_abs_value"] = float(np.abs(outputs["dense"]).max())
            row["speedup"] = row["dense"]["seconds"] / row["sparse"]["seconds"]
            cold = row["sparse"]["cold_seconds"]
            row["speedup_cold"] = row["dense"]["seconds"] / cold if cold else None
            row["memory_ratio"] = row["dense"]["peak_extra_mb"] / max(row["sparse"]["peak_extra_mb"], 1e-3)
            rows.append(row)
    return rows


def train_table(args: argparse.Namespace) -> list[dict]:
    presets = [(0.1, 0.5)] if args.quick else [(0.05, 1.0), (0.1, 0.5)]
    rows = []
    for voxel, width in presets:
        for net in ("minkunet", "spvcnn"):
            argv = ["--child", "train", "--net", net, "--voxel", str(voxel), "--width", str(width)]
            argv += ["--steps", str(args.steps), "--budget", str(args.budget)]
            row = {
                "net": net,
                "voxel_size": voxel,
                "width": width,
                "batch": 2,
                **run_child(argv, args.threads),
            }
            print(f"  train {net} {voxel} m w{width}: {row['steps_per_second']:.3f} steps/s", flush=True)
            rows.append(row)
    return rows


def print_tables(conv_rows: list[dict], train_rows: list[dict]) -> None:
    print("\nsparse vs dense conv (C -> C), forward, median seconds; memory = extra peak RSS in MB")
    head = f"{'voxel':>6} {'op':>5} {'voxels':>7} {'grid':>14} {'sparse':>8} {'cold':>8} {'dense':>8}"
    print(head + f" {'speedup':>8} {'mem sp':>8} {'mem de':>8} {'max|diff|':>10}")
    for r in conv_rows:
        grid = "x".join(str(g) for g in r["dense"]["grid"])
        print(
            f"{r['voxel_size']:>6} {r['op']:>5} {r['sparse']['voxels_in']:>7} {grid:>14} "
            f"{r['sparse']['seconds']:>8.4f} {r['sparse']['cold_seconds'] or float('nan'):>8.4f} "
            f"{r['dense']['seconds']:>8.3f} {r['speedup']:>7.1f}x {r['sparse']['peak_extra_mb']:>8.1f} "
            f"{r['dense']['peak_extra_mb']:>8.1f} {r['max_abs_diff']:>10.2e}"
        )
    print("\ntraining at batch 2 on real scans (AdamW, cross-entropy)")
    head = f"{'net':>9} {'voxel':>6} {'width':>6} {'params':>10} {'voxels/batch':>12}"
    print(head + f" {'steps/s':>8} {'s/step':>7} {'steps':>5} {'peak MB':>8}")
    for r in train_rows:
        print(
            f"{r['net']:>9} {r['voxel_size']:>6} {r['width']:>6} {r['parameters']:>10} "
            f"{r['voxels_per_batch'][0]:>12} {r['steps_per_second']:>8.3f} {r['step_seconds']:>7.2f} "
            f"{r['timed_steps']:>5} {r['peak_extra_mb']:>8.0f}"
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="submanifold conv only, fewer reps, 2 train steps")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--channels", type=int, default=32)
    parser.add_argument("--reps", type=int, default=None, help="sparse repetitions (dense: half)")
    parser.add_argument("--steps", type=int, default=None, help="timed training steps per net")
    parser.add_argument("--budget", type=float, default=None, help="seconds per training case (then stop)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "segmentation" / "sparse.json")
    parser.add_argument("--skip-train", action="store_true")
    # child-process arguments
    parser.add_argument("--child", choices=["conv", "train"], help=argparse.SUPPRESS)
    parser.add_argument("--method", choices=["sparse", "dense"], help=argparse.SUPPRESS)
    parser.add_argument("--op", choices=["sub", "down", "up"], help=argparse.SUPPRESS)
    parser.add_argument("--voxel", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--net", help=argparse.SUPPRESS)
    parser.add_argument("--width", type=float, default=1.0, help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.child == "conv":
        print(json.dumps(conv_child(args)))
        return 0
    if args.child == "train":
        print(json.dumps(train_child(args)))
        return 0
    if not (SEQUENCE / "velodyne" / "000000.bin").is_file():
        print(f"real scans not found at {SEQUENCE}", file=sys.stderr)
        return 1
    args.reps = args.reps or (2 if args.quick else 5)
    args.steps = args.steps or (2 if args.quick else 5)
    args.budget = args.budget or (60.0 if args.quick else 180.0)
    with tempfile.TemporaryDirectory() as tmp:
        conv_rows = conv_table(args, Path(tmp))
    train_rows = [] if args.skip_train else train_table(args)
    print_tables(conv_rows, train_rows)
    atomic_write_json(
        args.out,
        {
            "command": " ".join(["python", "benchmarks/bench_sparse.py", *sys.argv[1:]]),
            "machine": host_info(),
            "threads": args.threads,
            "crop_m": {"xy_abs_lt": CROP_XY, "z": [-CROP_Z, CROP_Z]},
            "memory_method": "VmHWM after a clear_refs reset minus VmRSS before; one subprocess per case",
            "conv": conv_rows,
            "train": train_rows,
        },
    )
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
