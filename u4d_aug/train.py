"""Training of one diffusion stage: `u4d train-diffusion CONFIG stage=stage1|stage2|u4d|baseline|detail [key=value ..]`.

Stage 1 learns x0_u (the projected uncertain region P_u) with a mask head (L_u), stage 2 learns the full scan x0
given concat(x0_u, m_u) (L_c), the baseline learns x0 unconditionally (R2DM); U4D paper §2. A cascade's detail
net learns x0 given every s-th column of it, as stage 2 does given P_u (`u4d_aug.cascade`).
The loop reads top to bottom (nanoGPT `train.py`): batch -> loss = diffusion(x0, cond, m_u) -> AdamW -> EMA, on
the run layer (`u4d_aug.run`: output folder, resolved config, log, checkpoints, clock) and the batches of
`u4d_aug.batches`, whose scans and noise of step s depend only on (seed, step, rank), so a resumed run ends as an
uninterrupted one. With `frames` = L > 1 a batch item is L consecutive scans (`frame_stride` apart) of one sequence,
tensors (B, L, C, H, W), and a net with MoST blocks mixes the frames; their mean gates are logged and plotted.
Checkpoints (`u4d_aug.stage.checkpoint_state`) are written atomically by rank 0; torchrun gives DDP through
`init_distributed`.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from u4d_aug.batches import RangeImages, crop_loss_weight, stage_inputs, training_batch
from u4d_aug.config import add_run_arguments, load_config, parse_override
from u4d_aug.diffusion import GaussianDiffusion
from u4d_aug.distributed import DistInfo, all_reduce_mean, barrier, cleanup, init_distributed
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.io import append_jsonl
from u4d_aug.latent import LatentNet, encode_item, load_latent_autoencoder
from u4d_aug.memory import check_net_fits
from u4d_aug.nn.unet import RangeUNet
from u4d_aug.progress import progress_bar
from u4d_aug.run import LOG_NAME, Clock, Start, begin_run, open_run, restore, save_checkpoint
from u4d_aug.runlock import run_lock
from u4d_aug.stage import (  # the stage contract (u4d_aug/stage.py)
    CHECKPOINT_KIND,
    DiffusionOptimConfig,
    DiffusionTrainConfig,
    build_net,
    checkpoint_state,
    config_from_checkpoint,
    diffusion_overrides,
    diffusion_recipe,
)
from u4d_aug.validate import check_finite_loss

logger = logging.getLogger(__name__)


def learning_rate(step: int, cfg: DiffusionOptimConfig, steps: int, time_fraction: float = 0.0) -> float:
    """Linear warm-up over warmup_steps, then constant, or a cosine from lr down to min_lr_ratio · lr at the last of
    `steps` (R2DM's decay) or once `time_fraction` of a wall-clock budget is used, whichever comes first."""
    warm = min(1.0, (step + 1) / max(1, cfg.warmup_steps))
    if cfg.schedule == "constant" or step < cfg.warmup_steps:
        return cfg.lr * warm
    progress = (step - cfg.warmup_steps) / max(1, steps - 1 - cfg.warmup_steps)  # 0 after warm-up .. 1 at the end
    progress = max(progress, time_fraction)
    floor = cfg.min_lr_ratio
    return cfg.lr * (floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress))))


def train(cfg: DiffusionTrainConfig, resume: str | Path | None = None, progress: bool = True) -> dict:
    """Train one stage; returns the last logged record. Writes OUT/{config.yaml, log.jsonl, hosts.jsonl, checkpoints/}.

    Rank 0 holds the run lock of OUT (`u4d_aug.runlock`) for the whole run: a second run on OUT is refused.
    """
    check_net_fits(lambda: build_net(cfg, "meta"), "the net of net.*", "reduce net.base_channels or other net sizes")
    info: DistInfo = init_distributed(cfg.device)
    with run_lock(cfg.out, enabled=info.is_main):
        return train_locked(cfg, info, resume, progress)


def train_locked(cfg: DiffusionTrainConfig, info: DistInfo, resume: str | Path | None, progress: bool) -> dict:
    """The run of `train` once OUT is locked: set-up, loop, log, checkpoint, done."""
    out = Path(cfg.out)
    start = open_run(out, resume, info.is_main, CHECKPOINT_KIND, "u4d train-diffusion")
    autoencoder = load_latent_autoencoder(cfg, info.device) if cfg.autoencoder else None  # a latent generator's
    encode = functools.partial(encode_item, autoencoder, cfg.latent_factor) if autoencoder is not None else None
    images = RangeImages(cfg, encode)  # a latent generator learns the latents of the range images
    net = build_net(cfg, info.device)
    if start.checkpoint is None and cfg.init_from:  # a resumed run has its own weights
        start_from(net, cfg, info.is_main)
    diffusion = GaussianDiffusion(net, cfg.diffusion, latent=autoencoder is not None)
    optim = cfg.optim
    optimizer = torch.optim.AdamW(net.parameters(), lr=optim.lr, betas=optim.betas, weight_decay=optim.weight_decay)
    ema = EMA(net, cfg.ema_decay, cfg.ema_warmup_steps)
    check_resumed_stage(start, cfg)
    restore(start, cfg, net, optimizer, ema, ignore=("out",))
    begin_run(out, cfg, start, info)
    model = distributed(diffusion, info)
    loss_weight = crop_loss_weight(cfg, info.device)  # (crop_width,) 0 on a crop's margins; None: every column

    record, window, gate_window, gate_plot = {}, [], [], []  # gates: (M, 2) per step since the last log / plot
    clock, tic = Clock(cfg.max_minutes, start.elapsed), time.perf_counter()
    bar = progress_bar(
        range(start.step, cfg.steps), initial=start.step, total=cfg.steps, enabled=(progress and info.is_main),
        desc=f"train {cfg.diffusion.stage}",
    )  # fmt: skip
    for step in bar:
        batch, offsets, generator = training_batch(images, cfg, step, info.rank, info.device)
        x0, cond, m_u = stage_inputs(cfg.diffusion.stage, batch)
        lr = learning_rate(step, optim, cfg.steps, clock.fraction() if optim.schedule == "cosine" else 0.0)
        for group in optimizer.param_groups:
            group["lr"] = lr

        losses = model(x0, cond, m_u, generator, offsets, batch.get("motion"), loss_weight)
        check_finite_loss(losses["loss"], step + 1)
        optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        grad_norm = nn.utils.clip_grad_norm_(net.parameters(), optim.grad_clip if optim.grad_clip > 0 else float("inf"))
        check_finite_loss(losses["loss"], step + 1, grad_norm)  # NaN weights would follow: stop before the step
        optimizer.step()
        ema.update(net)

        window.append(
            {k: float(all_reduce_mean(v.detach())) for k, v in losses.items()} | {"grad_norm": float(grad_norm)}
        )
        if net.most_names:  # the mean MoST gates of the step over ranks, (M, 2)
            gate_window.append(all_reduce_mean(net.gate_weights().to(info.device)).cpu().numpy())
            if info.is_main and cfg.sample_every > 0:
                gate_plot.append(gate_window[-1])
        done = step + 1
        elapsed, stop = clock.read()
        if done % cfg.log_every == 0 or done == cfg.steps or stop:
            record = log_record(done, lr, elapsed, time.perf_counter() - tic, window, gate_window, net.most_names)
            if info.is_main:
                append_jsonl(out / LOG_NAME, record)
                bar.set_postfix(loss=f"{record['loss']:.4f}")
            window, gate_window, tic = [], [], time.perf_counter()
        if info.is_main and cfg.sample_every > 0 and done % cfg.sample_every == 0:
            save_figures(net, ema, cfg, images, gate_plot, done, out / "samples", info.device)
            gate_plot = []
        if done % cfg.checkpoint_every == 0 or done == cfg.steps or stop:
            if info.is_main:
                save_checkpoint(out, checkpoint_state(cfg, done, net, ema, optimizer, elapsed), cfg.keep_checkpoints)
            barrier()
        if stop:
            if info.is_main:
                bar.write(f"stopping at step {done}: wall-clock budget of {cfg.max_minutes} min used")
            break
    bar.close()
    return record


def check_resumed_stage(start: Start, cfg: DiffusionTrainConfig) -> None:
    """A checkpoint resumes only the stage it trained."""
    if start.checkpoint is None:
        return
    old = config_from_checkpoint(start.checkpoint, str(start.path))
    if old.diffusion.stage != cfg.diffusion.stage:
        raise InputError(f"{start.path}: trained stage {old.diffusion.stage}, asked to resume as {cfg.diffusion.stage}")


def distributed(diffusion: GaussianDiffusion, info: DistInfo) -> nn.Module:
    """The module the loop calls: DDP around the diffusion under torchrun, the diffusion itself in one process."""
    if info.world_size == 1:
        return diffusion
    return nn.parallel.DistributedDataParallel(
        diffusion, device_ids=[info.device.index] if info.device.type == "cuda" else None
    )


def log_record(
    step: int, lr: float, elapsed: float, seconds: float, window: list[dict], gates: list[np.ndarray], blocks: list
) -> dict:
    """The log line of the steps of `window` (per-step means over ranks): their mean losses and grad norm, the mean
    MoST gates (α^s, α^t) per block when the net has them."""
    record = {"step": step, "lr": lr, "time": round(elapsed, 3), "sec_per_step": seconds / len(window)}
    record |= {k: float(np.mean([w[k] for w in window])) for k in window[0]}
    if gates:
        mean = np.mean(gates, axis=0, dtype=np.float64)  # (M, 2)
        record |= {"most_blocks": blocks, "most_alpha_s": mean[:, 0].round(4).tolist()}
        record["most_alpha_t"] = mean[:, 1].round(4).tolist()
    return record


def save_figures(
    net: RangeUNet,
    ema: EMA,
    cfg: DiffusionTrainConfig,
    images: RangeImages,
    gates: list[np.ndarray],
    step: int,
    folder: Path,
    device: torch.device,
) -> None:
    """FOLDER/step_XXXXXXX.png, a sample of the EMA net, and with MoST blocks FOLDER/gates_XXXXXXX.png."""
    sampler_net: nn.Module = build_net(cfg, device).eval()
    ema.copy_to(sampler_net)
    if cfg.autoencoder:
        sampler_net = LatentNet(sampler_net, load_latent_autoencoder(cfg, device))
    _save_sample_png(sampler_net, cfg, images, folder / f"step_{step:07d}.png")
    if gates:
        _save_gate_png(net, gates, step, folder / f"gates_{step:07d}.png")


def start_from(net: RangeUNet, cfg: DiffusionTrainConfig, announce: bool = False) -> list[str]:
    """Load the EMA weights of the trained net `cfg.init_from` into `net`; returns the names of the tensors only
    `net` has (they keep their init: MoST blocks and the pose embedding start as the identity), logged if `announce`."""
    from u4d_aug import pipeline

    source, source_cfg = pipeline.load_generator(cfg.init_from)
    if source_cfg.diffusion.stage != cfg.diffusion.stage:
        raise InputError(
            f"init_from: {cfg.init_from} is a {source_cfg.diffusion.stage} net, this run trains {cfg.diffusion.stage}"
        )
    weights, target = source.state_dict(), net.state_dict()
    foreign = sorted(name for name in weights if name not in target or weights[name].shape != target[name].shape)
    if foreign:
        raise InputError(
            f"init_from: {cfg.init_from} has tensors this net lacks or shapes unlike its ({', '.join(foreign[:3])}); "
            "only MoST blocks and the pose embedding may be added (net.most, net.pose_dim)"
        )
    net.load_state_dict(weights, strict=False)
    added = sorted({name.split(".")[0] for name in set(target) - set(weights)})
    if announce:
        logger.info("%s: started from %s; new tensors %s", cfg.out, cfg.init_from, ", ".join(added) or "none")
        check_source_recipe(source_cfg, cfg)
    return added


def check_source_recipe(source_cfg: DiffusionTrainConfig, cfg: DiffusionTrainConfig) -> dict[str, tuple]:
    """The diffusion settings (`stage.diffusion_recipe`) in which this fine-tune differs from its init_from net,
    {key: (source's, this run's)}, logged as a warning naming the overrides that would match them."""
    source, mine = diffusion_recipe(source_cfg.diffusion), diffusion_recipe(cfg.diffusion)
    differs = {key: (value, mine[key]) for key, value in source.items() if mine[key] != value}
    if differs:
        keys = {f"diffusion.{key}" for key in differs}
        same = [override for override in diffusion_overrides(source_cfg.diffusion) if override.split("=")[0] in keys]
        logger.warning(
            "%s: init_from %s was trained with other diffusion settings (%s); to fine-tune on its recipe pass %s",
            cfg.out, cfg.init_from, ", ".join(f"{k}: {a!r} there, {b!r} here" for k, (a, b) in differs.items()),
            " ".join(same),
        )  # fmt: skip
    return differs


def _save_sample_png(net: nn.Module, cfg: DiffusionTrainConfig, images: RangeImages, path: Path) -> None:
    """An ancestral DDPM sample of the EMA net (stage 2: completing the first item's x0_u) as a PNG, L depth rows."""
    import matplotlib.pyplot as plt

    from u4d_aug import pipeline
    from u4d_aug.sampling_settings import SamplingSettings
    from u4d_aug.trajectory import straight_motion
    from u4d_aug.viz import draw_range_image, save_figure

    generator = torch.Generator().manual_seed(cfg.seed)
    device = next(net.parameters()).device
    # the net's own ancestral DDPM at every step: no stage-1 options, no mean start (no stored mean while training)
    ddpm = SamplingSettings(
        sampler="ddpm", steps=cfg.sample_steps, stage1_steps=None, stage1_mask_fraction=None, mean_start_below=None
    )
    motion = None
    if cfg.net.pose_dim:  # an ego-motion net drives 1 m per frame straight ahead
        motion = torch.from_numpy(straight_motion(cfg.frames, 1.0))  # (L, 4)
        motion = motion[None] if cfg.frames > 1 else motion  # (1, L, 4), or (1, 4) for single frames
    if cfg.diffusion.stage == "u4d":
        x0 = pipeline.generate_u4d((net, cfg), (net, cfg), 1, generator, ddpm, motion=motion)["x0"]
    elif cfg.diffusion.stage == "stage2":
        first = RangeImages(cfg)[0] if images.encode is not None else images[0]  # complete() takes range images
        x0_u, m_u = first["x0_u"][None].to(device), first["m_u"][None].to(device)
        motion = first["motion"][None] if "motion" in first else None  # the window's own
        x0 = pipeline.complete((net, cfg), x0_u, m_u, generator, ddpm, motion=motion)["x0"]
    elif cfg.diffusion.stage == "detail":  # the first training scan's layout, completed
        x_low = images[0]["x0_u"][None, :, :, :: cfg.detail_stride].to(device)
        x0 = pipeline.refine((net, cfg), x_low, generator, ddpm)["x0"]
    elif cfg.diffusion.stage == "stage1":
        x0 = pipeline.generate_stage1((net, cfg), 1, generator, ddpm, motion=motion)["x0_u"]
    else:
        x0 = pipeline.generate_baseline((net, cfg), 1, generator, ddpm, motion=motion)["x0"]
    frames = (x0[0] if x0.dim() == 5 else x0[:1]).cpu().numpy()  # (L, 2, H, W)
    fig, axes = plt.subplots(len(frames) + 1, 1, figsize=(10, 1.5 * (len(frames) + 1)))
    for index, frame in enumerate(frames):
        which = f", frame {index}" if len(frames) > 1 else ""
        title = f"{cfg.diffusion.stage} depth (EMA, DDPM {cfg.sample_steps}{which})"
        draw_range_image(axes[index], frame[0], title, vmin=-1, vmax=1, unit="log-depth x0 [-1, 1]")
    draw_range_image(axes[-1], frames[0, 1], "reflectance" + (", frame 0" if len(frames) > 1 else ""), vmin=-1,
                     vmax=1, unit="intensity x0 [-1, 1]")  # fmt: skip
    save_figure(fig, path)


def _save_gate_png(net: RangeUNet, gates: list[np.ndarray], step: int, path: Path) -> None:
    """Bar chart of the MoST gates (α^s, α^t) per block, averaged over the training steps since the last one."""
    from u4d_aug.viz import plot_gate_weights

    mean = np.mean(gates, axis=0)  # (M, 2)
    title = f"MoST gate weights, training steps {step - len(gates) + 1}-{step}"
    plot_gate_weights(path, net.most_names, mean[:, 0], mean[:, 1], title)


def split_stage_override(overrides: list[str]) -> list[str]:
    """`stage=X` is the short form of `diffusion.stage=X`."""
    out = []
    for item in overrides:
        key = item.partition("=")[0].strip()
        out.append("diffusion." + item.strip() if key == "stage" else item)
    for item in out:
        parse_override(item)  # one-line error for a malformed override before any work
    return out


def add_train_diffusion_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d train-diffusion CONFIG stage=stage1|stage2|u4d|baseline|detail [key=value ..] [--resume]
    [--out]`."""
    add_run_arguments(
        parser, "configs/u4d/cpu.yaml", "stage=stage1 steps=100 (stage=stage1|stage2|u4d|baseline|detail)"
    )


def run_train_diffusion(args: argparse.Namespace) -> int:
    """`u4d train-diffusion`: train stage 1, stage 2 or the baseline (torchrun for several processes)."""
    cfg = load_config(DiffusionTrainConfig, args.config, split_stage_override(list(args.overrides)))
    if args.out is not None:
        cfg = dataclasses.replace(cfg, out=str(args.out))
    try:
        train(cfg, resume=args.resume, progress=not args.no_progress)
    finally:
        cleanup()
    return 0
