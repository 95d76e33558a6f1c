"""How well each generator fills what propagation leaves unknown, against what it was trained to fill (real truth).

    python benchmarks/diagnostics/diag_propagation_fill.py --root data/sim_seg --probs data/sim_seg_probs_heldout \
        --sequences 88-93 --out benchmarks/results/temporal/propagation_fill

With `propagate=true` (`u4d_aug.propagate`) frames 1..L-1 of a sequence are frame 0 moved along the poses (~70 % of
the pixels) plus what the net fills in; U4D's stage 2 was trained to complete around P_u (~10 % known, paper §2).
Here real held-out windows are the truth (the first --frames frames of each sequence, their real poses). Two known
regions per window, each filled by every net (`--nets`; default the shipped 4D and single-frame nets) from the same
seed: "propagated", real frame 0 moved into frames 1..L-1 (`warp_frame0`, as propagation does with a generated
frame 0), and "uncertain", each frame's own P_u (top-k entropy from --probs, as stage 2 trains). Stage-2 nets (a
one-net u4d checkpoint as `NAME=WEIGHTS@stage2`, its stage-2 task) fill with `pipeline.complete`, baselines with
`pipeline.inpaint` (x̂0 pinned where known); the known pixels are kept
exactly, as propagation keeps them. Scored on frames 1..L-1, on the pixels left unknown, against the real frame:
`returns` the share where generated and real agree on return / no return, `mae_m` the mean |depth error| (m) where
both return, `seam_m` the mean depth step across a known-unknown horizontal neighbour pair (real: `seam_real_m`, the
same pairs of the real frame). Mean ± std over windows (ddof 1).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from u4d_aug.data.datasets import open_sequences
from u4d_aug.data.sensors import get_sensor
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, training_mean
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text
from u4d_aug.pipeline import MeanStart, complete, inpaint, load_generator
from u4d_aug.propagate import warp_frame0
from u4d_aug.range_view import NO_RETURN, decode_depth, project, to_image
from u4d_aug.sampling_settings import SamplingSettings
from u4d_aug.trajectory import relative_motion
from u4d_aug.uncertainty import load_probs, probs_path, uncertain_range_view

REPO = Path(__file__).resolve().parents[2]
SHIPPED = [
    f"{name}={REPO / 'weights' / file}"
    for name, file in (
        ("u4d_most_stage2", "u4d_most_stage2.pt"),
        ("baseline_most", "baseline_most.pt"),
        ("u4d", "u4d.pt@stage2"),  # the one net's stage-2 task
        ("baseline", "baseline.pt"),
    )
]
CONDITIONS = ("propagated", "uncertain")
METRICS = ("known", "returns", "mae_m", "seam_m", "seam_real_m")


def real_window(item: dict, cfg, probs_root: Path) -> dict[str, Tensor]:
    """The real frames x0 (L, 2, H, W) and both known regions (x0_u (L, 2, H, W), m_u (L, 1, H, W)) of one window."""
    sensor = get_sensor(cfg.sensor)
    x0 = torch.stack(
        [to_image(project(points, sensor, cfg.height, cfg.width, cfg.row_mode), sensor) for points in item["points"]]
    )
    warped_u, warped_m = warp_frame0(x0[0], item["poses"], sensor, cfg.row_mode)
    uncertain = []
    for points, frame in zip(item["points"], item["frames"], strict=True):
        probs = load_probs(probs_path(str(probs_root), item["seq"], frame), points.shape[0])
        x0_u, m_u, _ = uncertain_range_view(
            points, probs, sensor, cfg.height, cfg.width, cfg.row_mode, cfg.uncertainty.k, cfg.uncertainty.strategy
        )
        uncertain.append((x0_u, m_u))
    return {
        "x0": x0,
        "propagated": (warped_u, warped_m),
        "uncertain": (torch.stack([u for u, _ in uncertain]), torch.stack([m for _, m in uncertain])),
    }


def fill(
    loaded, x0_u: Tensor, m_u: Tensor, motion: Tensor, steps: int, sampler: str, seed: int, pin: bool = False
) -> Tensor:
    """One net's completion of a window (L, 2, H, W) around x0_u where m_u is 1, known pixels kept exactly; `pin`:
    stage 2's x̂0 pinned to them at every step too (`complete(pin_known=True)`)."""
    net, cfg = loaded
    sequence = cfg.frames > 1  # a MoST net takes the window as one (1, L, ...) sequence, others frame by frame
    batch_u, batch_m = (x0_u[None], m_u[None]) if sequence else (x0_u, m_u)
    pose = motion[None] if cfg.net.pose_dim else None
    generator = torch.Generator().manual_seed(seed)
    settings = SamplingSettings(sampler=sampler, steps=steps, mean_start_below=None)  # `loaded`: in its MeanStart
    with torch.no_grad():
        if cfg.diffusion.stage in ("stage2", "u4d"):  # a u4d net: its stage-2 task (`complete`)
            x0 = complete(loaded, batch_u, batch_m, generator, settings, pose, pin)["x0"]
        else:  # `inpaint` refuses any net but a baseline
            x0 = inpaint(loaded, batch_u, batch_m, generator, settings, pose)["x0"]
    x0 = x0[0] if sequence else x0
    return torch.where(m_u.bool(), x0_u, x0.to(x0_u.dtype))


def fill_scores(generated: Tensor, real: Tensor, m_u: Tensor, max_range: float) -> dict[str, float]:
    """Scores of generated frames (F, 2, H, W) against the real ones on the pixels m_u (F, 1, H, W) leaves unknown."""
    unknown = ~m_u[:, 0].bool()  # (F, H, W)
    gen_hit, real_hit = generated[:, 0] > NO_RETURN, real[:, 0] > NO_RETURN
    gen_depth, real_depth = decode_depth(generated[:, 0], max_range), decode_depth(real[:, 0], max_range)
    both = unknown & gen_hit & real_hit
    known = ~unknown
    # known-unknown horizontal neighbours (ring wrap included) where both pixels return in both images
    pairs = (known & torch.roll(unknown, -1, -1)) | (unknown & torch.roll(known, -1, -1))
    returns_all = gen_hit & real_hit & torch.roll(gen_hit & real_hit, -1, -1)
    pairs = pairs & returns_all
    gen_step = (gen_depth - torch.roll(gen_depth, -1, -1)).abs()
    real_step = (real_depth - torch.roll(real_depth, -1, -1)).abs()
    nan = float("nan")
    return {
        "known": float(known.float().mean()),
        "returns": float((gen_hit == real_hit)[unknown].float().mean()) if unknown.any() else nan,
        "mae_m": float((gen_depth - real_depth).abs()[both].mean()) if both.any() else nan,
        "seam_m": float(gen_step[pairs].mean()) if pairs.any() else nan,
        "seam_real_m": float(real_step[pairs].mean()) if pairs.any() else nan,
    }


def summary(rows: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Mean and sample std (ddof 1; 0 for one window) of each score over windows, NaN-free windows only."""
    out = {}
    for key in METRICS:
        values = np.array([row[key] for row in rows], dtype=np.float64)
        values = values[np.isfinite(values)]
        std = float(values.std(ddof=1)) if len(values) > 1 else 0.0
        out[key] = {"mean": float(values.mean()) if len(values) else float("nan"), "std": std, "n": len(values)}
    return out


def to_markdown(result: dict) -> str:
    """One row per (condition, net)."""
    lines = [
        f"# Filling around propagation vs around P_u ({result['windows']} real windows of {result['frames']} frames, "
        f"{result['root']} {' '.join(result['sequences'])})",
        "",
        f"{result['sampler']}, {result['steps']} steps, mean start below log-SNR {result['mean_start_below']}"
        + ("; stage 2's x̂0 pinned to the known pixels at every step" if result["pin_known"] else "")
        + "; "
        "frames 1..L-1, unknown pixels, against the real frame. known = share of pixels given; returns = return / "
        "no-return agreement; MAE = mean |depth error| where both return; seam = mean depth step across known-unknown "
        "neighbours (real: the same pairs in the real frame). Mean ± std over windows.",
        "",
        "| condition | net | known | returns ↑ | MAE (m) ↓ | seam (m) | seam real (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for condition in CONDITIONS:
        for name, net in result["nets"].items():
            s = net[condition]
            cells = [f"{s[k]['mean']:.3f} ± {s[k]['std']:.3f}" for k in METRICS]
            lines.append(f"| {condition} | {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--nets", nargs="+", default=SHIPPED, metavar="NAME=WEIGHTS",
        help="stage-2 / baseline nets; a one-net u4d checkpoint as NAME=WEIGHTS@stage2",
    )  # fmt: skip
    parser.add_argument("--root", type=Path, required=True, help="SemanticKITTI root with poses (held-out places)")
    parser.add_argument("--probs", type=Path, required=True, help="seg-predict probabilities of ROOT (P_u)")
    parser.add_argument("--sequences", nargs="+", default=["88-93"], help="sequences of ROOT (names, A-B ranges)")
    parser.add_argument("--frames", type=int, default=5, help="frames per window (the first window of each sequence)")
    parser.add_argument("--steps", type=int, default=20, help="sampling steps")
    parser.add_argument("--sampler", default="dpmpp2m-sde", help="ddpm | ddim | dpmpp2m | dpmpp2m-sde")
    parser.add_argument("--mean-start-below", type=float, default=-10.0, help="mean start (generate_hdl64.yaml)")
    parser.add_argument("--mean-data-root", default="", help="scans for a net's mean image when its file has none")
    parser.add_argument("--seed", type=int, default=0, help="window i is filled from seed + i by every net")
    parser.add_argument("--pin-known", action="store_true", help="stage 2: x̂0 pinned to the known pixels every step")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "temporal" / "propagation_fill")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        if args.frames < 2:
            raise InputError(f"--frames must be >= 2 (frame 0 is propagated into the others), got {args.frames}")
        dataset = open_sequences(args.root, args.frames, args.sequences)
        firsts = [(seq, i) for i, (seq, start) in enumerate(dataset.windows) if start == 0]  # a window per sequence
        nets = {}
        for spec in args.nets:
            name, sep, weights = spec.rpartition("=")
            if not sep or not name or not weights:
                raise InputError(f"--nets {spec!r}: expected NAME=WEIGHTS[@stage2]")
            path, _, role = weights.partition("@")
            net, cfg = load_generator(path)
            if cfg.diffusion.stage not in ("stage2", "baseline", "u4d"):
                raise InputError(
                    f"--nets {name}: a {cfg.diffusion.stage} net; expected stage2, baseline or u4d@stage2 nets"
                )
            if (cfg.diffusion.stage == "u4d") != (role == "stage2"):
                raise InputError(f"--nets {spec!r}: @stage2 names the stage-2 task of a one-net u4d checkpoint")
            role = role or cfg.diffusion.stage  # the mean of the images it fills: x0
            mean, _ = training_mean(cfg, role, GenerateConfig(mean_data_root=args.mean_data_root), Path(path))
            nets[name] = ((MeanStart(net, mean, args.mean_start_below), cfg), weights)
        shapes = {(cfg.sensor, cfg.height, cfg.width, cfg.row_mode) for (_, cfg), _ in nets.values()}
        if len(shapes) != 1:
            raise InputError(f"--nets: every net must share sensor, image size and row mode, got {sorted(shapes)}")
        first_cfg = next(iter(nets.values()))[0][1]
        max_range = get_sensor(first_cfg.sensor).max_range
        rows = {name: {c: [] for c in CONDITIONS} for name in nets}
        for w, (seq, index) in enumerate(firsts):
            item = dataset[index]
            window = real_window(item, first_cfg, args.probs)
            motion = torch.from_numpy(relative_motion(item["poses"]))  # (L, 4)
            for name, (loaded, _) in nets.items():
                for condition in CONDITIONS:
                    x0_u, m_u = window[condition]
                    generated = fill(loaded, x0_u, m_u, motion, args.steps, args.sampler, args.seed + w, args.pin_known)
                    rows[name][condition].append(fill_scores(generated[1:], window["x0"][1:], m_u[1:], max_range))
            print(f"window {w + 1}/{len(firsts)} (sequence {seq}) filled by {len(nets)} nets", flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = {
        "benchmark": "propagation_fill",
        "command": " ".join(sys.argv),
        "root": str(args.root),
        "sequences": args.sequences,
        "windows": len(firsts),
        "frames": args.frames,
        "steps": args.steps,
        "sampler": args.sampler,
        "mean_start_below": args.mean_start_below,
        "pin_known": args.pin_known,
        "seed": args.seed,
        "nets": {
            name: {"weights": str(path)} | {c: summary(rows[name][c]) for c in CONDITIONS}
            for name, (_, path) in nets.items()
        },
        "per_window": rows,
        "host": host_info(),
    }
    out = args.out
    atomic_write_json(out.with_suffix(".json"), result)
    atomic_write_text(out.with_suffix(".md"), to_markdown(result))
    print(to_markdown(result))
    print(f"-> {out.with_suffix('.json')}, {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
