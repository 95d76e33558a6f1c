"""Is the generators' missing street a precision problem? Refine a sample's last x̂0 by a K-draw consensus and ask the
gates.

    python benchmarks/diagnostics/consensus_refine.py --net ../runs/final/baseline_milestones/step_12000.pt \
        --num 8 --log-snr 5 8 --k 8 --out ../runs/consensus
    python benchmarks/gates.py --bank none=../runs/consensus/none --bank median_5=../runs/consensus/median_5 ... \
        --real data/sim_eval --real-sequences 00-11 --num 8

A baseline net (`--net`, R2DM-style, weights or checkpoint) samples `--num` scans with the generate preset's sampler
(DPM-Solver++(2M) SDE, 20 steps, the mean start unless --no-mean-start; scan i seeded SEED + i). Each scan's x̂0 is
then noised again to a log-SNR λ with K independent draws, x_t = α x̂0 + σ ε_k, denoised by one net call each and
combined per pixel by the mean or the median of the K estimates (a one-call x̂0's error at λ is partly the net's
variance, which averaging over draws removes; the median keeps depth edges). Every variant is written as a
SemanticKITTI-layout folder OUT/none, OUT/{mean,median}_λ of the decoded points for `benchmarks/gates.py` and
`benchmarks/diagnostics/plot_bev_folders.py` (findings: `results/generation/pilots.md`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

from u4d_aug.data.formats import write_kitti_scan
from u4d_aug.diffusion import alpha_sigma
from u4d_aug.errors import InputError
from u4d_aug.pipeline import denoiser, generate_baseline, load_generator, to_points
from u4d_aug.progress import progress_bar
from u4d_aug.sampling import DenoiseFn
from u4d_aug.sampling_settings import DEFAULT_SAMPLING

HOWS = ("mean", "median")


def consensus(
    denoise: DenoiseFn, x0: torch.Tensor, lam: float, k: int, how: str, generator: torch.Generator
) -> torch.Tensor:
    """x0 (N, C, H, W) noised to log-SNR `lam` with k draws each, one ε̂ call per draw, the k estimates of x0
    (clamped to [-1, 1]) combined per pixel by their mean or median: (N, C, H, W)."""
    if how not in HOWS:
        raise ValueError(f"how must be one of {HOWS}, got {how!r}")
    alpha, sigma = (float(v) for v in alpha_sigma(torch.tensor(lam, dtype=torch.float64)))
    estimates = []
    for _ in range(k):
        eps = torch.randn(x0.shape, generator=generator)
        x_t = alpha * x0 + sigma * eps
        with torch.no_grad():
            out = denoise(x_t, torch.full((x0.shape[0],), lam), None)
        eps_hat = out[0] if isinstance(out, tuple) else out
        estimates.append(((x_t - sigma * eps_hat) / alpha).clamp(-1.0, 1.0))
    stacked = torch.stack(estimates)  # (k, N, C, H, W)
    return stacked.mean(0) if how == "mean" else stacked.median(0).values


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--net", type=Path, required=True, help="a baseline (R2DM-style) net: weights or checkpoint")
    parser.add_argument("--num", type=int, default=8, help="scans")
    parser.add_argument("--seed", type=int, default=1000, help="scan i is sampled with seed SEED + i")
    parser.add_argument("--log-snr", type=float, nargs="+", default=[5.0, 8.0], help="refinement noise levels λ")
    parser.add_argument("--k", type=int, default=8, help="noise draws per scan and λ")
    parser.add_argument("--no-mean-start", action="store_true", help="the net's own x̂0 at every step")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", type=Path, required=True, help="folder of the variants' scan folders")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        if args.num < 1 or args.k < 1:
            raise InputError(f"--num and --k must be >= 1, got {args.num} and {args.k}")
        if args.out.exists() and any(args.out.iterdir()):
            raise InputError(f"--out {args.out}: not empty (the variants' folders go into a new folder)")
        loaded = load_generator(args.net)
        cfg = loaded.config
        if cfg.diffusion.stage != "baseline" or cfg.latent_factor:
            raise InputError(f"--net {args.net}: a range-image baseline net, got stage {cfg.diffusion.stage!r}")
        settings = dataclasses.replace(DEFAULT_SAMPLING, mean_start_below=None if args.no_mean_start else -10.0)
        samples = [
            generate_baseline(loaded, 1, [torch.Generator().manual_seed(args.seed + i)], settings)["x0"]
            for i in progress_bar(range(args.num), desc="sampling", unit="scan")
        ]
        x0 = torch.cat(samples)  # (N, 2, H, W)
        denoise = denoiser(loaded, (args.num,))
        variants = {"none": x0}
        for lam in args.log_snr:
            for how in HOWS:
                generator = torch.Generator().manual_seed(args.seed)  # the same draws for mean and median
                variants[f"{how}_{lam:g}"] = consensus(denoise, x0, lam, args.k, how, generator)
        for name, images in variants.items():
            folder = args.out / name / "sequences" / "00" / "velodyne"
            folder.mkdir(parents=True, exist_ok=True)
            for i, points in enumerate(to_points(images, cfg.sensor, cfg.row_mode)):
                write_kitti_scan(folder / f"{i:06d}.bin", points)
            print(f"{name}: {args.num} scans in {folder.parents[2]}", flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
