"""`u4d gates CKPT --png OUT [--json]`: what the MoST gates of a trained sequence net do while it samples.

The paper observes that spatial mixing dominates near the input and output and temporal mixing in the middle of
the UNet (U4D §2, MoST analysis). Here one L-frame sequence is sampled (ancestral DDPM by default) and after every
net call the batch-mean gates (α^s, α^t) of each MoST block (depth order enc -> mid -> dec) are recorded with the
call's log-SNR: a (steps, blocks) table per gate, its mean per block over the whole sampling and over its first,
middle and last third (high -> low noise). Gates near ½ do not mean the branches are equal: a branch conv can grow
or shrink while its gate stays put, so each call also records the RMS of what each branch adds (α^s F^s, α^t F^t)
and the temporal share of the update, RMS(α^t F^t) / (RMS(α^s F^s) + RMS(α^t F^t)), per block. Stage 2 samples
with an empty condition (no uncertain region); a one-net u4d samples the task of `--role` (stage 1 or stage 2, with
that same empty condition); a net with an ego-motion condition drives `--step` metres per frame, straight ahead.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_text
from u4d_aug.trajectory import straight_motion

PHASES = ("high noise", "middle", "low noise")


def gate_trajectory(
    loaded: tuple,
    frames: int,
    steps: int,
    generator: torch.Generator,
    sampler: str = "ddpm",
    step: float = 1.0,
    role: str = "stage2",
) -> dict:
    """Gates of every net call while sampling one L-frame sequence: log_snr (S,), alpha_s / alpha_t (S, M); `role`
    (stage1 | stage2): the task a one-net u4d samples (other nets have one)."""
    from u4d_aug.diffusion import STAGE1_TASK, STAGE2_TASK, stage_cond
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
    inputs: dict = {}
    if cfg.net.pose_dim:
        inputs["poses"] = torch.from_numpy(straight_motion(frames, step))[None]  # (1, L, 4)
    if role not in ("stage1", "stage2"):
        raise InputError(f"gates: --role must be stage1 or stage2, got {role!r}")
    if cfg.net.num_tasks:  # a one-net u4d: which stage it samples (both read the empty condition here)
        inputs["task"] = STAGE1_TASK if role == "stage1" else STAGE2_TASK
    log_snrs, gates, updates = [], [], []

    def denoise(x, lam, c):
        out = net(x, lam, c, **inputs)
        log_snrs.append(float(lam.reshape(-1)[0]))
        gates.append(net.gate_weights().cpu().numpy())  # (M, 2)
        updates.append(net.branch_updates().cpu().numpy())  # (M, 3)
        return out

    blocks = net.most_blocks()
    for block in blocks:
        block.record_updates = True
    try:
        with torch.no_grad():
            sample(sampler, denoise, shape, steps, generator, cond=cond)
    finally:
        for block in blocks:
            block.record_updates = False
    table, rms = np.stack(gates).astype(np.float64), np.stack(updates).astype(np.float64)  # (S, M, 2), (S, M, 3)
    return {
        "blocks": list(net.most_names),
        "log_snr": log_snrs,
        "alpha_s": table[..., 0],
        "alpha_t": table[..., 1],
        "rms_x": rms[..., 0],
        "rms_s": rms[..., 1],
        "rms_t": rms[..., 2],
    }


def temporal_share(trajectory: dict) -> np.ndarray:
    """(S, M) RMS(α^t F^t) / (RMS(α^s F^s) + RMS(α^t F^t)); ½ where both branches add nothing (an untrained block)."""
    rms_s, rms_t = trajectory["rms_s"], trajectory["rms_t"]
    total = rms_s + rms_t
    return np.where(total > 0, rms_t / np.maximum(total, 1e-30), 0.5)


def summarise_gates(trajectory: dict) -> dict:
    """Per block, over all steps and per third of the sampling: gates, the update's temporal share and size (json)."""
    alpha_s, alpha_t, share = trajectory["alpha_s"], trajectory["alpha_t"], temporal_share(trajectory)
    thirds = np.array_split(np.arange(len(alpha_t)), 3)

    def by_phase(table: np.ndarray) -> dict:
        return {phase: table[idx].mean(axis=0).round(4).tolist() for phase, idx in zip(PHASES, thirds) if len(idx)}

    rms_x = np.maximum(trajectory["rms_x"], 1e-30)
    return {
        "blocks": trajectory["blocks"],
        "mean_alpha_s": alpha_s.mean(axis=0).round(4).tolist(),
        "mean_alpha_t": alpha_t.mean(axis=0).round(4).tolist(),
        "alpha_t_by_phase": by_phase(alpha_t),
        "mean_temporal_share": share.mean(axis=0).round(4).tolist(),
        "temporal_share_by_phase": by_phase(share),
        "mean_update_s_over_x": (trajectory["rms_s"] / rms_x).mean(axis=0).round(4).tolist(),
        "mean_update_t_over_x": (trajectory["rms_t"] / rms_x).mean(axis=0).round(4).tolist(),
        "log_snr": [round(v, 4) for v in trajectory["log_snr"]],
        "alpha_t": alpha_t.round(4).tolist(),
    }


def plot_gates(path: str | Path, trajectory: dict, title: str = "") -> Path:
    """α^t and the update's temporal share per block for each third of the sampling; α^t over (step, block)."""
    from u4d_aug.viz import plt, save_figure

    summary = summarise_gates(trajectory)
    blocks, alpha_t = summary["blocks"], trajectory["alpha_t"]
    depth = np.arange(len(blocks))
    fig, (gate_ax, share_ax, heat_ax) = plt.subplots(
        1, 3, figsize=(15.0, 3.6), gridspec_kw={"width_ratios": [1, 1, 1.3]}
    )
    panels = (
        (gate_ax, summary["alpha_t_by_phase"], r"mean gate $\alpha^t$ (temporal); $\alpha^s = 1 - \alpha^t$"),
        (share_ax, summary["temporal_share_by_phase"], r"temporal share of the update: $|\alpha^t F^t| / \Sigma$"),
    )
    for ax, phases, label in panels:
        for phase, values in phases.items():
            ax.plot(depth, values, marker="o", label=phase)
        ax.axhline(0.5, color="gray", linewidth=0.8, linestyle="--")
        ax.set_xticks(depth, blocks)
        ax.set_ylim(0.0, 1.0)
        ax.set_xlabel("MoST block (input -> output)")
        ax.set_ylabel(label, fontsize=9)
        ax.legend(fontsize=8)
    spread = max(float(np.abs(alpha_t - 0.5).max()), 0.01)  # the colour range follows the data around ½
    image = heat_ax.imshow(
        alpha_t, aspect="auto", cmap="coolwarm", vmin=0.5 - spread, vmax=0.5 + spread, interpolation="nearest"
    )
    heat_ax.set_xticks(depth, blocks)
    heat_ax.set_ylabel("sampling step (noisy -> clean)")
    heat_ax.set_title(rf"$\alpha^t$ (colour range 0.5 ± {spread:.2f})", fontsize=9)
    fig.colorbar(image, ax=heat_ax, fraction=0.04)
    fig.suptitle(title or "MoST gates while sampling", fontsize=10)
    return save_figure(fig, path)


def add_gates_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d gates CKPT --png OUT [--json] [--frames L] [--steps S] [--seed S] [--role stage1|stage2]`."""
    parser.add_argument("checkpoint", type=Path, help="train-diffusion checkpoint, run folder or exported weights")
    parser.add_argument("--png", type=Path, required=True, help="figure to write")
    parser.add_argument("--json", action="store_true", help="also print the gate table as json")
    parser.add_argument("--frames", type=int, default=None, help="L (default: the frames the net was trained on)")
    parser.add_argument("--steps", type=int, default=32, help="DDPM steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--step", type=float, default=1.0, help="metres per frame for nets with an ego-motion input")
    parser.add_argument(
        "--role", choices=["stage1", "stage2"], default="stage2", help="the stage a one-net u4d samples (stage=u4d)"
    )


def run_gates(args: argparse.Namespace) -> int:
    """`u4d gates`: the MoST gate analysis of a trained sequence net (figure, optional json)."""
    from u4d_aug.pipeline import load_generator

    if args.frames is not None and args.frames < 1:
        raise InputError(f"--frames {args.frames}: expected L >= 1 (leave it out for the frames the net trained on)")
    if args.steps < 1:
        raise InputError(f"--steps {args.steps}: expected >= 1")
    if not math.isfinite(args.step):
        raise InputError(f"--step {args.step}: expected a finite number of metres per frame")
    loaded = load_generator(args.checkpoint)
    frames = args.frames if args.frames is not None else loaded.config.frames
    generator = torch.Generator().manual_seed(args.seed)
    trajectory = gate_trajectory(loaded, frames, args.steps, generator, step=args.step, role=args.role)
    stage = loaded.config.diffusion.stage + (f" {args.role}" if loaded.config.net.num_tasks else "")
    title = f"{args.checkpoint} ({stage}, L={frames}, DDPM {args.steps})"
    plot_gates(args.png, trajectory, title)
    summary = summarise_gates(trajectory)
    if args.json:
        print(json.dumps(summary))
    else:
        rows = zip(summary["blocks"], summary["mean_alpha_s"], summary["mean_alpha_t"], summary["mean_temporal_share"])
        for name, s, t, share in rows:
            print(f"{name}: alpha_s {s:.3f}  alpha_t {t:.3f}  temporal share of the update {share:.3f}")
    atomic_write_text(Path(args.png).with_suffix(".json"), json.dumps(summary, indent=1))
    return 0
