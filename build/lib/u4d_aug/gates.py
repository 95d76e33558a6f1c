"""`u4d gates CKPT --png OUT [--json]`: what the MoST gates of a trained sequence net do while it samples.

The paper observes that spatial mixing dominates near the input and output and temporal mixing in the middle of
the UNet (U4D §2, MoST analysis). Here one L-frame sequence is sampled (ancestral DDPM by default) and after every
net call the batch-mean gates (α^s, α^t) of each MoST block (depth order enc -> mid -> dec) are recorded with the
call's log-SNR: a (steps, blocks) table per gate, its mean per block over the whole sampling and over its first,
middle and last third (high -> low noise). Stage 2 samples with an empty condition (no uncertain region); a net
with an ego-motion condition drives `--step` metres per frame, straight ahead.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_text
from u4d_aug.trajectory import straight_motion

PHASES = ("high noise", "middle", "low noise")


def gate_trajectory(
    loaded: tuple, frames: int, steps: int, generator: torch.Generator, sampler: str = "ddpm", step: float = 1.0
) -> dict:
    """Gates of every net call while sampling one L-frame sequence: log_snr (S,), alpha_s / alpha_t (S, M)."""
    from u4d_aug.diffusion import stage_cond
    from u4d_aug.sampling import sample

    net, cfg = loaded
    if not net.most_names or cfg.net.most_fusion != "gating":
        raise InputError("gates: the checkpoint has no gated MoST blocks (net.most=true, net.most_fusion=gating)")
    if frames < 1 or steps < 1:
        raise InputError(f"gates: --frames and --steps must be >= 1, got {frames}, {steps}")
    shape = (1, frames, cfg.net.in_channels, cfg.height, cfg.width)
    cond = None
    if cfg.net.cond_channels:  # stage 2: an empty uncertain region
        empty = torch.full((1, frames, 2, cfg.height, cfg.width), -1.0)
        cond = stage_cond(empty, torch.zeros(1, frames, 1, cfg.height, cfg.width))
    poses = None
    if cfg.net.pose_dim:
        poses = torch.from_numpy(straight_motion(frames, step))[None]  # (1, L, 4)
    log_snrs, gates = [], []

    def denoise(x, lam, c):
        out = net(x, lam, c, poses=poses) if poses is not None else net(x, lam, c)
        log_snrs.append(float(lam.reshape(-1)[0]))
        gates.append(net.gate_weights().cpu().numpy())  # (M, 2)
        return out

    with torch.no_grad():
        sample(sampler, denoise, shape, steps, generator, cond=cond)
    table = np.stack(gates)  # (S, M, 2)
    return {"blocks": list(net.most_names), "log_snr": log_snrs, "alpha_s": table[..., 0], "alpha_t": table[..., 1]}


def summarise_gates(trajectory: dict) -> dict:
    """Mean α^s / α^t per block over all steps and over the three thirds of the sampling (json-ready)."""
    alpha_s, alpha_t = trajectory["alpha_s"], trajectory["alpha_t"]
    thirds = np.array_split(np.arange(len(alpha_t)), 3)
    return {
        "blocks": trajectory["blocks"],
        "mean_alpha_s": alpha_s.mean(axis=0).round(4).tolist(),
        "mean_alpha_t": alpha_t.mean(axis=0).round(4).tolist(),
        "alpha_t_by_phase": {
            phase: alpha_t[idx].mean(axis=0).round(4).tolist() for phase, idx in zip(PHASES, thirds) if len(idx)
        },
        "log_snr": [round(v, 4) for v in trajectory["log_snr"]],
        "alpha_t": alpha_t.round(4).tolist(),
    }


def plot_gates(path: str | Path, trajectory: dict, title: str = "") -> Path:
    """Left: mean α^t per block for each third of the sampling; right: α^t over (sampling step, block)."""
    from u4d_aug.viz import plt, save_figure

    summary = summarise_gates(trajectory)
    blocks, alpha_t = summary["blocks"], trajectory["alpha_t"]
    depth = np.arange(len(blocks))
    fig, (left, right) = plt.subplots(1, 2, figsize=(11.0, 3.4), gridspec_kw={"width_ratios": [1, 1.3]})
    for phase, values in summary["alpha_t_by_phase"].items():
        left.plot(depth, values, marker="o", label=phase)
    left.axhline(0.5, color="gray", linewidth=0.8, linestyle="--")
    left.set_xticks(depth, blocks)
    left.set_ylim(0.0, 1.0)
    left.set_xlabel("MoST block (input -> output)")
    left.set_ylabel(r"mean $\alpha^t$ (temporal); $\alpha^s = 1 - \alpha^t$")
    left.legend(fontsize=8)
    image = right.imshow(alpha_t, aspect="auto", cmap="coolwarm", vmin=0.0, vmax=1.0, interpolation="nearest")
    right.set_xticks(depth, blocks)
    right.set_ylabel("sampling step (noisy -> clean)")
    right.set_title(r"$\alpha^t$", fontsize=9)
    fig.colorbar(image, ax=right, fraction=0.04)
    fig.suptitle(title or "MoST gates while sampling", fontsize=10)
    return save_figure(fig, path)


def add_gates_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d gates CKPT --png OUT [--json] [--frames L] [--steps S] [--seed S]`."""
    parser.add_argument("checkpoint", type=Path, help="train-diffusion checkpoint, run folder or exported weights")
    parser.add_argument("--png", type=Path, required=True, help="figure to write")
    parser.add_argument("--json", action="store_true", help="also print the gate table as json")
    parser.add_argument("--frames", type=int, default=None, help="L (default: the frames the net was trained on)")
    parser.add_argument("--steps", type=int, default=32, help="DDPM steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--step", type=float, default=1.0, help="metres per frame for nets with an ego-motion input")


def run_gates(args: argparse.Namespace) -> int:
    """`u4d gates`: the MoST gate analysis of a trained sequence net (figure, optional json)."""
    from u4d_aug.pipeline import load_generator

    loaded = load_generator(args.checkpoint)
    frames = args.frames or loaded[1].frames
    trajectory = gate_trajectory(loaded, frames, args.steps, torch.Generator().manual_seed(args.seed), step=args.step)
    title = f"{args.checkpoint} ({loaded[1].diffusion.stage}, L={frames}, DDPM {args.steps})"
    plot_gates(args.png, trajectory, title)
    summary = summarise_gates(trajectory)
    if args.json:
        print(json.dumps(summary))
    else:
        for name, s, t in zip(summary["blocks"], summary["mean_alpha_s"], summary["mean_alpha_t"]):
            print(f"{name}: alpha_s {s:.3f}  alpha_t {t:.3f}")
    atomic_write_text(Path(args.png).with_suffix(".json"), json.dumps(summary, indent=1))
    return 0
