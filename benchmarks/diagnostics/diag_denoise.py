"""How much noise each generator removes in one call, by log-SNR: the precision of a few-step sampler's last x̂0.

    python benchmarks/diagnostics/diag_denoise.py --root data/sim_eval --probs data/sim_eval_probs --sequences 00 \
        --num 4 --out benchmarks/results/generation/denoise_64x1024.json

Each net (`--nets NAME=WEIGHTS ...`; a one-net u4d checkpoint as `NAME=WEIGHTS@stage1` or `@stage2` for one of its
two tasks; default the shipped baseline and the shipped one-net U4D's stage-2 and stage-1 tasks) reads the first
`--num` scans of ROOT's SEQUENCES as its training target: the scan's range image x0 (the baseline; stage 2,
conditioned on the scan's own P_u from --probs) or x0_u, the P_u pixels (stage 1). The target is noised to
x_t = α x0 + σ ε at each log-SNR of --log-snr (ε drawn from --seed, the same for every net) and the net called
once: x̂0 = clamp((x_t − σ ε̂)/α).
Reported on the pixels holding a return: the mean |x̂0 − x0| beside the noise it started from, mean |x_t/α − x0| (a
net that removes nothing scores the same), and the roughness (`range_view.image_roughness`) of x̂0 against x0's.
The samplers hand back the x̂0 of their last call, whose log-SNR the table states for 20 and 32 steps.

The second table follows whole sampler trajectories (`--sampler`, default the shipped preset's dpmpp2m-sde, 20 steps,
time grid; NAME:STEPS:logsnr for the grid uniform in log-SNR, which ends at a higher log-SNR): up to each log-SNR of
--from-log-snr the sampler is handed the real x0 as its x̂0 (`sampling.replace_known` over the whole image, so x_t is
the real scan noised as q(x_t | x0)), from there on the net's; reported: the last x̂0's error, roughness (of the
pixels that decode to a point within the sensor's range, as `u4d generate` writes them: x̂0 just above −1 where the
scan has no return is no point) and above-ground points per occupied BEV cell (`metrics.structure.points_per_cell`)
beside the real scans'. A net that denoises one call well but keeps the error of its own earlier x̂0 (exposure bias)
scores far worse here than in the one-call table; a sampler whose last call sits at a low log-SNR keeps that call's
error whatever the trajectory before it.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

from u4d_aug.batches import RangeImages, stage_inputs
from u4d_aug.data.sensors import get_sensor
from u4d_aug.diffusion import STAGE1_TASK, STAGE2_TASK, alpha_sigma, log_snr, stage_cond
from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text
from u4d_aug.metrics.structure import points_per_cell
from u4d_aug.pipeline import denoiser, load_generator, to_points
from u4d_aug.range_view import NO_RETURN, image_roughness, unproject
from u4d_aug.sampling import SAMPLER_NAMES, check_grid, log_snr_grid, replace_known, sample

REPO = Path(__file__).resolve().parents[2]
SHIPPED = [
    f"{name}={REPO / 'weights' / file}{role}"
    for name, file, role in (
        ("baseline", "baseline.pt", ""),
        ("u4d stage 2", "u4d.pt", "@stage2"),  # the one net's two tasks
        ("u4d stage 1", "u4d.pt", "@stage1"),
    )
]
LOG_SNRS = [0.0, 2.0, 5.0, 8.0, 11.0, 14.0]


def targets(
    cfg, root: Path, probs: Path | None, sequences: list[str], num: int, role: str | None = None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(target (N, 2, H, W), net condition or None) of the first `num` scans, as the net's stage (a u4d net: the
    stage `role`) trains on them."""
    stage = role if cfg.diffusion.stage == "u4d" else cfg.diffusion.stage
    probs_root = str(probs) if probs is not None else ""
    view = dataclasses.replace(
        cfg, data_root=str(root), probs_root=probs_root, sequences=sequences, frames=1, cache_images=False
    )
    images = RangeImages(view)  # a u4d net's view reads x0, x0_u and m_u
    items = [images[i] for i in range(min(num, len(images)))]
    batch = {key: torch.stack([item[key] for item in items]) for key in items[0]}
    target, cond, m_u = stage_inputs(stage, batch)
    return target, stage_cond(cond, m_u) if stage == "stage2" else None


def denoise_rows(net, target: torch.Tensor, cond, lams: list[float], seed: int) -> list[dict]:
    # net: a denoise function (`pipeline.denoiser`): ε̂ (and an extra output) of (x_t, log-SNR, cond)
    """One ε̂ call per log-SNR on the noised target: x̂0's error and roughness against the noise it started from."""
    valid = target[:, 0] > NO_RETURN
    generator = torch.Generator().manual_seed(seed)
    rows = []
    for lam in lams:
        alpha, sigma = (float(v) for v in alpha_sigma(torch.tensor(lam, dtype=torch.float64)))
        eps = torch.randn(target.shape, generator=generator)
        x_t = alpha * target + sigma * eps
        with torch.no_grad():
            out = net(x_t, torch.full((target.shape[0],), lam), cond)
            eps_hat = out[0] if isinstance(out, tuple) else out
        x0_hat = ((x_t - sigma * eps_hat) / alpha).clamp(-1.0, 1.0)
        rows.append(
            {
                "log_snr": lam,
                "sigma_over_alpha": sigma / alpha,
                "noise": float((x_t / alpha - target)[:, 0].abs()[valid].mean()),
                "error": float((x0_hat - target)[:, 0].abs()[valid].mean()),
                "roughness": image_roughness(torch.where(valid[:, None], x0_hat, -1.0))[0],
            }
        )
    return rows


def trajectory_rows(
    net,
    target: torch.Tensor,
    cond,
    starts: list[float],
    sampler: str,
    steps: int,
    sensor,
    row_mode: str,
    seed: int,
    grid: str = "time",
) -> list[dict]:
    """The sampler run with the real target as x̂0 below each start log-SNR and the net from there: the last x̂0's
    error, roughness and BEV points per cell (sample i seeded seed + i, the same for every start)."""
    valid = target[:, 0] > NO_RETURN
    everywhere = torch.ones_like(target)
    real = replace_known(net, target, everywhere)
    rows = []
    for start in starts:

        def handed(x_t, lam, c, start=start):  # the real scan's x̂0 before `start`, the net's from there
            return real(x_t, lam, c) if float(lam.reshape(-1)[0]) < start else net(x_t, lam, c)

        generators = [torch.Generator().manual_seed(seed + i) for i in range(target.shape[0])]
        with torch.no_grad():
            x0_hat = sample(sampler, handed, tuple(target.shape), steps, generators, cond=cond, grid=grid).x0
        returns = unproject(x0_hat, sensor, row_mode)[1]  # (N, H, W): pixels that decode to a point, as in a bank
        rows.append(
            {
                "from_log_snr": start,
                "error": float((x0_hat - target)[:, 0].abs()[valid].mean()),
                "roughness": image_roughness(torch.where(returns[:, None], x0_hat, -1.0))[0],
                "bev_points_per_cell": points_per_cell(to_points(x0_hat, sensor, row_mode)),
            }
        )
    return rows


def to_markdown(result: dict) -> str:
    """One row per log-SNR: each net's |x̂0 − x0| / noise and x̂0's roughness."""
    names = list(result["nets"])
    last = result["last_call_log_snr"]
    lines = [
        f"# One denoising call by log-SNR ({result['num']} scans of {result['root']} {' '.join(result['sequences'])})",
        "",
        f"The samplers' last call (time grid): log-SNR {last['20']:.2f} at 20 steps, {last['32']:.2f} at 32 steps. "
        "error = mean |x̂0 − x0| on returns (encoded depth, [-1, 1]); noise = the same for x_t/α (no denoising); "
        "rough = x̂0's horizontal roughness.",
        "",
        "| log-SNR | σ/α | " + " | ".join(f"{n}: error / noise | {n}: rough" for n in names) + " |",
        "|---|---|" + "---|---|" * len(names),
        "| real target | — | " + " | ".join(f"— | {result['nets'][n]['real_roughness']:.4f}" for n in names) + " |",
    ]
    for i, lam in enumerate(result["log_snrs"]):
        cells = []
        for name in names:
            row = result["nets"][name]["rows"][i]
            cells.append(f"{row['error']:.4f} / {row['noise']:.4f} | {row['roughness']:.4f}")
        sigma = result["nets"][names[0]]["rows"][i]["sigma_over_alpha"]
        lines.append(f"| {lam:g} | {sigma:.4f} | " + " | ".join(cells) + " |")
    if result.get("from_log_snrs"):
        sampler = result["sampler"]
        lines += [
            "",
            f"## Sampler trajectories ({sampler['name']}, {sampler['steps']} steps, {sampler['grid']} grid, last "
            f"call at log-SNR {sampler['last_call_log_snr']:.2f}) handed the real scan below a start log-SNR",
            "",
            "Last x̂0: error = mean |x̂0 − x0| on returns; rough = horizontal roughness; BEV = above-ground points per "
            "occupied 0.25 m cell.",
            "",
            "| from log-SNR | " + " | ".join(f"{n}: error | {n}: rough | {n}: BEV" for n in names) + " |",
            "|---|" + "---|---|---|" * len(names),
            "| real target | "
            + " | ".join(
                f"— | {result['nets'][n]['real_roughness']:.4f} | {result['nets'][n]['real_bev_points_per_cell']:.2f}"
                for n in names
            )
            + " |",
        ]
        for i, start in enumerate(result["from_log_snrs"]):
            cells = []
            for name in names:
                row = result["nets"][name]["trajectories"][i]
                cells.append(f"{row['error']:.4f} | {row['roughness']:.4f} | {row['bev_points_per_cell']:.2f}")
            lines.append(f"| {start:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nets", nargs="+", default=SHIPPED, metavar="NAME=WEIGHTS", help="generators to probe")
    parser.add_argument("--root", type=Path, required=True, help="SemanticKITTI root of real (held-out) scans")
    parser.add_argument("--probs", type=Path, default=None, help="seg-predict probabilities of ROOT (U4D stages)")
    parser.add_argument("--sequences", nargs="+", default=["00"], help="sequences of ROOT to read")
    parser.add_argument("--num", type=int, default=4, help="scans")
    parser.add_argument("--log-snr", type=float, nargs="+", default=LOG_SNRS, help="noise levels")
    parser.add_argument("--from-log-snr", type=float, nargs="*", default=[], help="trajectory starts (none: skip)")
    parser.add_argument("--sampler", default="dpmpp2m-sde:20", help="NAME:STEPS[:GRID] of the trajectories")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "generation" / "denoise.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    nets = {}
    try:
        if args.num < 1:
            raise InputError(f"--num must be >= 1, got {args.num}")
        sampler_name, _, rest = args.sampler.partition(":")
        steps_text, _, grid = rest.partition(":")
        grid = grid or "time"
        if sampler_name not in SAMPLER_NAMES or not steps_text.isdigit() or int(steps_text) < 1:
            raise InputError(
                f"--sampler {args.sampler!r}: expected NAME:STEPS[:GRID], NAME one of {', '.join(SAMPLER_NAMES)}"
            )
        try:
            check_grid(sampler_name, grid)
        except ValueError as exc:
            raise InputError(f"--sampler {args.sampler!r}: {exc}") from None
        for spec in args.nets:
            name, sep, path = spec.rpartition("=")
            if not sep or not name or not path:
                raise InputError(f"--nets {spec!r}: expected NAME=WEIGHTS[@stage1|@stage2]")
            path, _, role = path.partition("@")
            loaded = load_generator(path)
            cfg = loaded.config
            if (cfg.diffusion.stage == "u4d") != (role in ("stage1", "stage2")):
                raise InputError(f"--nets {spec!r}: @stage1 or @stage2 names the task of a one-net u4d checkpoint")
            task = {"stage1": STAGE1_TASK, "stage2": STAGE2_TASK}.get(role)
            target, cond = targets(cfg, args.root, args.probs, args.sequences, args.num, role or None)
            net = denoiser(loaded, (target.shape[0],), task=task)
            nets[name] = {
                "weights": path,
                "stage": cfg.diffusion.stage,
                "real_roughness": image_roughness(target)[0],
                "rows": denoise_rows(net, target, cond, args.log_snr, args.seed),
            }
            if args.from_log_snr:
                sensor, row_mode = get_sensor(cfg.sensor), cfg.row_mode
                nets[name]["real_bev_points_per_cell"] = points_per_cell(to_points(target, sensor, row_mode))
                nets[name]["trajectories"] = trajectory_rows(
                    net,
                    target,
                    cond,
                    args.from_log_snr,
                    sampler_name,
                    int(steps_text),
                    sensor,
                    row_mode,
                    args.seed,
                    grid,
                )
            print(f"{name}: probed at {len(args.log_snr)} log-SNRs", flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = {
        "benchmark": "denoise",
        "command": " ".join(sys.argv),
        "machine": host_info(),
        "root": str(args.root),
        "sequences": args.sequences,
        "num": args.num,
        "seed": args.seed,
        "log_snrs": args.log_snr,
        "from_log_snrs": args.from_log_snr,
        "sampler": {
            "name": sampler_name,
            "steps": int(steps_text),
            "grid": grid,
            "last_call_log_snr": log_snr_grid(int(steps_text), grid)[-2],
        },
        "last_call_log_snr": {str(n): float(log_snr(torch.tensor(1.0 / n, dtype=torch.float64))) for n in (20, 32)},
        "nets": nets,
    }
    text = to_markdown(result)
    print(text)
    atomic_write_json(args.out, result)
    atomic_write_text(args.out.with_suffix(".md"), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
