"""Training of one diffusion stage: `u4d train-diffusion CONFIG stage=stage1|stage2|baseline [key=value ..]`.

Stage 1 learns x0_u (the projected uncertain region P_u) with a mask head (L_u), stage 2 learns the full scan x0
given concat(x0_u, m_u) (L_c), the baseline learns x0 unconditionally (R2DM); U4D paper §2.
The loop reads top to bottom (nanoGPT `train.py`): batch -> loss = diffusion(x0, cond, m_u) -> AdamW -> EMA.
With `frames` = L > 1 a batch item is L consecutive scans (`frame_stride` apart) of one sequence, tensors
(B, L, C, H, W), and a net with MoST blocks mixes the frames; their mean gates are logged and plotted.
The scans of step s and the noise of step s depend only on (seed, step, rank), so a resumed run draws what an
uninterrupted one would. Checkpoints hold config, step, model, EMA, optimizer and RNG and are written
atomically by rank 0; torchrun gives DDP through `init_distributed`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from u4d_aug.config import add_run_arguments, config_to_dict, load_config, parse_override, save_config
from u4d_aug.data.beams import check_beams
from u4d_aug.data.datasets import (
    NuscenesScanDataset,
    NuscenesSequenceDataset,
    ScanDataset,
    SequenceDataset,
    open_scans,
    open_sequences,
)
from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.diffusion import GaussianDiffusion
from u4d_aug.distributed import DistInfo, all_reduce_mean, barrier, budget_used, cleanup, init_distributed
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import append_jsonl, atomic_torch_save, atomic_write_text, load_checkpoint, read_jsonl
from u4d_aug.nn.unet import RangeUNet, crop_columns
from u4d_aug.progress import progress_bar
from u4d_aug.range_view import project, to_image
from u4d_aug.runfolder import prepare, resume_point
from u4d_aug.runlock import run_lock
from u4d_aug.seeding import derived_seed
from u4d_aug.stage import (  # the stage contract (u4d_aug/stage.py)
    CHECKPOINT_KIND,
    DiffusionOptimConfig,
    DiffusionTrainConfig,
    build_net,
    config_from_checkpoint,
)
from u4d_aug.trajectory import relative_motion
from u4d_aug.uncertainty import load_probs, probs_path, uncertain_range_view
from u4d_aug.validate import check_finite_loss
from u4d_aug.weights import is_exported

logger = logging.getLogger(__name__)

_BATCH, _NOISE = 1, 2  # streams of derived_seed


class RangeImages:
    """Item i = dict(x0 (2, H, W), x0_u (2, H, W), m_u (1, H, W)) of scan i; x0_u/m_u need probabilities.

    With cfg.frames = L > 1, item i stacks the L scans of window i of a `SequenceDataset` (one sequence,
    frame_stride apart): x0 (L, 2, H, W), x0_u (L, 2, H, W), m_u (L, 1, H, W); poses are not needed.
    x0_u and m_u are recomputed per scan for strategy 'random' (seeded by `generator`), cached otherwise.
    """

    def __init__(self, cfg: DiffusionTrainConfig) -> None:
        if not cfg.data_root:
            raise InputError("data_root: expected a SemanticKITTI-layout folder (or a nuScenes root) of training scans")
        self.cfg = cfg
        self.sensor: Sensor = get_sensor(cfg.sensor)
        layout = (cfg.data_format, cfg.nuscenes_version)
        self.scans: ScanDataset | NuscenesScanDataset = open_scans(cfg.data_root, cfg.sequences, False, *layout)
        if len(self.scans) == 0:
            raise InputError(f"{cfg.data_root}: no scans found")
        first = self.scans.entries[0]
        check_beams(self.scans.load_points(*first), self.sensor, f"{cfg.data_root}: scan {'/'.join(first)}")
        self.windows: SequenceDataset | NuscenesSequenceDataset | None = None
        if cfg.frames > 1:
            self.windows = open_sequences(
                cfg.data_root, cfg.frames, cfg.sequences, cfg.frame_stride, cfg.net.pose_dim > 0, *layout
            )
        self.needs_probs = cfg.diffusion.stage in ("stage1", "stage2") and cfg.uncertainty.strategy != "none"
        if self.needs_probs and not cfg.probs_root:
            raise InputError(
                f"probs_root: stage {cfg.diffusion.stage} needs the probability files of `u4d seg-predict`"
            )
        self.cache: dict[tuple[str, str], dict[str, Tensor]] = {}

    def __len__(self) -> int:
        return len(self.windows) if self.windows is not None else len(self.scans)

    def window(self, index: int) -> tuple[str, list[str]]:
        """(sequence, frame names) of item `index`: one scan, or the L scans of a window."""
        if self.windows is None:
            seq, frame = self.scans.entries[index]
            return seq, [frame]
        seq, start = self.windows.windows[index]
        stop = start + self.cfg.frames * self.cfg.frame_stride
        return seq, self.windows.frames[seq][start : stop : self.cfg.frame_stride]

    def __getitem__(self, index: int, generator: torch.Generator | None = None) -> dict[str, Tensor]:
        seq, frames = self.window(index)
        if self.windows is None:
            return self.scan_images(seq, frames[0], generator)
        items = [self.scan_images(seq, frame, generator) for frame in frames]
        out = {key: torch.stack([item[key] for item in items]) for key in items[0]}  # (L, C, H, W) each
        if self.cfg.net.pose_dim:  # the ego motion of the window's frames, (L, 4) in the first frame's sensor frame
            start = self.windows.windows[index][1]
            positions = list(range(start, start + self.cfg.frames * self.cfg.frame_stride, self.cfg.frame_stride))
            out["motion"] = torch.from_numpy(relative_motion(self.windows.poses[seq][positions]))
        return out

    def scan_images(self, seq: str, frame: str, generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """x0 (2, H, W) and, for stages 1 and 2, x0_u (2, H, W), m_u (1, H, W) of one scan (cached)."""
        if (seq, frame) in self.cache:
            return self.cache[(seq, frame)]
        cfg = self.cfg
        points = torch.from_numpy(self.scans.load_points(seq, frame))
        x0 = to_image(project(points, self.sensor, cfg.height, cfg.width, cfg.row_mode), self.sensor)
        out = {"x0": x0}
        if cfg.diffusion.stage != "baseline":
            if self.needs_probs:
                path = probs_path(cfg.probs_root, seq, frame)
                probs = load_probs(path, points.shape[0])
            else:
                probs = np.zeros((points.shape[0], 1), dtype=np.float32)
            x0_u, m_u, _ = uncertain_range_view(
                points, probs, self.sensor, cfg.height, cfg.width, cfg.row_mode,
                cfg.uncertainty.k, cfg.uncertainty.strategy, generator,
            )  # fmt: skip
            out.update(x0_u=x0_u, m_u=m_u)
        if cfg.cache_images and cfg.uncertainty.strategy != "random":
            self.cache[(seq, frame)] = out
        return out


def batch_indices(step: int, rank: int, num_scans: int, batch_size: int, seed: int) -> list[int]:
    """This rank's scan indices of `step`: uniform with replacement from a (seed, step, rank) stream."""
    rng = np.random.default_rng(derived_seed(seed, _BATCH, step, rank))
    return rng.integers(0, num_scans, batch_size).tolist()


def make_batch(images: RangeImages, indices: list[int], generator: torch.Generator, device: torch.device) -> dict:
    """Stack the items of `indices` into (B, [L,] C, H, W) tensors on `device`."""
    items = [images.__getitem__(i, generator) for i in indices]
    return {key: torch.stack([item[key] for item in items]).to(device) for key in items[0]}


def crop_offsets(batch_size: int, cfg: DiffusionTrainConfig, generator: torch.Generator) -> Tensor | None:
    """(B,) random first columns of the azimuth crops, multiples of the net's downsampling (None: no crop)."""
    if not cfg.crop_width:
        return None
    factor = cfg.net.downsampling_factor
    return factor * torch.randint(0, cfg.width // factor, (batch_size,), generator=generator)


IMAGE_KEYS = ("x0", "x0_u", "m_u")  # the range images of a batch; its other entries (the ego motion) are per frame


def crop_batch(batch: dict[str, Tensor], offsets: Tensor, crop_width: int) -> dict[str, Tensor]:
    """Azimuth crops (B, [L,] C, H, crop_width) of the batch's images (`IMAGE_KEYS`), wrapping around the ring."""
    out = dict(batch)
    for key in IMAGE_KEYS:
        if key not in batch:
            continue
        value = batch[key]
        columns = crop_columns(offsets.to(value.device), crop_width, value.shape[-1])  # (B, w)
        index = columns.view(value.shape[0], *([1] * (value.dim() - 2)), crop_width).expand(*value.shape[:-1], -1)
        out[key] = torch.gather(value, -1, index)
    return out


def stage_inputs(stage: str, batch: dict) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(x0, cond, m_u) of GaussianDiffusion.forward: stage 1 learns x0 := x0_u; stage 2 reads x0_u, m_u."""
    if stage == "stage1":
        return batch["x0_u"], None, batch["m_u"]
    if stage == "stage2":
        return batch["x0"], batch["x0_u"], batch["m_u"]
    return batch["x0"], None, None


def learning_rate(step: int, cfg: DiffusionOptimConfig) -> float:
    """Linear warm-up over warmup_steps, then constant (R2DM)."""
    return cfg.lr * min(1.0, (step + 1) / max(1, cfg.warmup_steps))


def save_checkpoint(path: Path, state: dict, keep: int) -> None:
    """Write atomically, then delete all but the newest `keep` step_*.pt beside it (0 = keep all)."""
    atomic_torch_save(path, state)
    if keep > 0:
        for old in sorted(path.parent.glob("step_*.pt"))[:-keep]:
            old.unlink(missing_ok=True)


def checkpoint_state(
    cfg: DiffusionTrainConfig,
    step: int,
    net: nn.Module,
    ema: EMA,
    optimizer: torch.optim.Optimizer | None = None,
    elapsed: float = 0.0,
) -> dict:
    """Everything a checkpoint holds: kind, resolved config, step, wall-clock seconds, model, EMA, optimizer, RNG."""
    return {
        "kind": CHECKPOINT_KIND,
        "config": config_to_dict(cfg),
        "step": step,
        "elapsed": elapsed,
        "model": net.state_dict(),
        "ema": ema.state_dict(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "rng": {"torch": torch.get_rng_state(), "seed": cfg.seed},
    }


def _save_sample_png(net: RangeUNet, cfg: DiffusionTrainConfig, images: RangeImages, path: Path) -> None:
    """An ancestral DDPM sample of the EMA net (stage 2: completing the first item's x0_u) as a PNG, L depth rows."""
    import matplotlib.pyplot as plt

    from u4d_aug import pipeline
    from u4d_aug.viz import draw_range_image, save_figure

    generator = torch.Generator().manual_seed(cfg.seed)
    device = next(net.parameters()).device
    if cfg.diffusion.stage == "stage2":
        first = images[0]
        x0 = pipeline.complete(
            (net, cfg),
            first["x0_u"][None].to(device),
            first["m_u"][None].to(device),
            cfg.sample_steps,
            generator,
            "ddpm",
        )["x0"]
    elif cfg.diffusion.stage == "stage1":
        x0 = pipeline.generate_stage1((net, cfg), 1, cfg.sample_steps, generator, "ddpm")["x0_u"]
    else:
        x0 = pipeline.generate_baseline((net, cfg), 1, cfg.sample_steps, generator, "ddpm")["x0"]
    frames = (x0[0] if x0.dim() == 5 else x0[:1]).cpu().numpy()  # (L, 2, H, W)
    fig, axes = plt.subplots(len(frames) + 1, 1, figsize=(10, 1.5 * (len(frames) + 1)))
    for index, frame in enumerate(frames):
        which = f", frame {index}" if len(frames) > 1 else ""
        title = f"{cfg.diffusion.stage} depth (EMA, DDPM {cfg.sample_steps}{which})"
        draw_range_image(axes[index], frame[0], title)
    draw_range_image(axes[-1], frames[0, 1], "reflectance" + (", frame 0" if len(frames) > 1 else ""))
    save_figure(fig, path)


def _save_gate_png(net: RangeUNet, gates: list[np.ndarray], step: int, path: Path) -> None:
    """Bar chart of the MoST gates (α^s, α^t) per block, averaged over the training steps since the last one."""
    from u4d_aug.viz import plot_gate_weights

    mean = np.mean(gates, axis=0)  # (M, 2)
    title = f"MoST gate weights, training steps {step - len(gates) + 1}-{step}"
    plot_gate_weights(path, net.most_names, mean[:, 0], mean[:, 1], title)


def start_from(net: RangeUNet, cfg: DiffusionTrainConfig) -> list[str]:
    """Load the EMA weights of the trained net `cfg.init_from` into `net`; returns the names of the tensors only
    `net` has (they keep their init: MoST blocks and the pose embedding start as the identity)."""
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
    return sorted({name.split(".")[0] for name in set(target) - set(weights)})


def train(cfg: DiffusionTrainConfig, resume: str | Path | None = None, progress: bool = True) -> dict:
    """Train one stage; returns the last logged record. Writes OUT/{config.yaml, log.jsonl, checkpoints/}.

    Rank 0 holds the run lock of OUT (`u4d_aug.runlock`) for the whole run: a second run on OUT is refused.
    """
    info: DistInfo = init_distributed(cfg.device)
    with run_lock(cfg.out, enabled=info.is_main):
        return train_locked(cfg, info, resume, progress)


def train_locked(cfg: DiffusionTrainConfig, info: DistInfo, resume: str | Path | None, progress: bool) -> dict:
    """The run of `train` once OUT is locked: set-up, resume point, loop."""
    out_dir = Path(cfg.out)
    log_path = out_dir / "log.jsonl"
    ckpt_path = resume_point(out_dir, resume)  # None: step 0 (also --resume before the first checkpoint)
    if info.is_main:
        prepare(out_dir, ckpt_path)
    images = RangeImages(cfg)
    net = build_net(cfg, info.device)
    if ckpt_path is None and cfg.init_from:  # a resumed run has its own weights
        added = start_from(net, cfg)
        if info.is_main:
            logger.info("%s: started from %s; new tensors %s", out_dir, cfg.init_from, ", ".join(added) or "none")
    diffusion = GaussianDiffusion(net, cfg.diffusion)
    optimizer = torch.optim.AdamW(
        net.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas, weight_decay=cfg.optim.weight_decay
    )
    ema = EMA(net, cfg.ema_decay, cfg.ema_warmup_steps)
    start, elapsed_before = 0, 0.0
    if ckpt_path is not None:
        ckpt = load_checkpoint(ckpt_path, "diffusion checkpoint to resume from")
        old = config_from_checkpoint(ckpt, str(ckpt_path))
        if is_exported(ckpt):
            raise InputError(f"{ckpt_path}: exported weights hold no optimizer or EMA state; resume from a step_*.pt")
        if old.diffusion.stage != cfg.diffusion.stage:
            raise InputError(
                f"{ckpt_path}: trained stage {old.diffusion.stage}, asked to resume as {cfg.diffusion.stage}"
            )
        net.load_state_dict(ckpt["model"])
        ema.load_state_dict(ckpt["ema"])
        optimizer.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["rng"]["torch"])
        start, elapsed_before = int(ckpt["step"]), float(ckpt.get("elapsed", 0.0))
        if info.is_main and log_path.exists():
            kept = [r for r in read_jsonl(log_path) if r.get("step", 0) <= start]
            atomic_write_text(log_path, "".join(json.dumps(r) + "\n" for r in kept))
    if info.is_main:
        save_config(cfg, out_dir / "config.yaml")
    model: nn.Module = diffusion
    if info.world_size > 1:
        model = nn.parallel.DistributedDataParallel(
            diffusion, device_ids=[info.device.index] if info.device.type == "cuda" else None
        )

    record: dict = {}
    window: list[dict[str, float]] = []
    gate_window: list[np.ndarray] = []  # (M, 2) mean MoST gates per step since the last log line
    gate_plot: list[np.ndarray] = []  # ... since the last gate plot
    tic = t0 = time.perf_counter()
    bar = progress_bar(
        range(start, cfg.steps),
        initial=start,
        total=cfg.steps,
        enabled=(progress and info.is_main),
        desc=f"train {cfg.diffusion.stage}",
    )
    for step in bar:
        generator = torch.Generator().manual_seed(derived_seed(cfg.seed, _NOISE, step, info.rank))
        indices = batch_indices(step, info.rank, len(images), cfg.batch_size, cfg.seed)
        batch = make_batch(images, indices, generator, info.device)
        offsets = crop_offsets(len(indices), cfg, generator)  # None: full panorama
        if offsets is not None:
            batch = crop_batch(batch, offsets, cfg.crop_width)
        x0, cond, m_u = stage_inputs(cfg.diffusion.stage, batch)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(step, cfg.optim)

        losses = model(x0, cond, m_u, generator, offsets, batch.get("motion"))
        check_finite_loss(losses["loss"], step + 1)
        optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        grad_norm = nn.utils.clip_grad_norm_(
            net.parameters(), cfg.optim.grad_clip if cfg.optim.grad_clip > 0 else float("inf")
        )
        check_finite_loss(losses["loss"], step + 1, grad_norm)  # NaN weights would follow: stop before the step
        optimizer.step()
        ema.update(net)

        window.append(
            {k: float(all_reduce_mean(v.detach())) for k, v in losses.items()} | {"grad_norm": float(grad_norm)}
        )
        if net.most_names:
            gates = all_reduce_mean(net.gate_weights().to(info.device)).cpu().numpy()  # (M, 2)
            gate_window.append(gates)
            if info.is_main and cfg.sample_every > 0:
                gate_plot.append(gates)
        done = step + 1
        elapsed = elapsed_before + time.perf_counter() - t0
        stop = budget_used(elapsed, cfg.max_minutes)
        if done % cfg.log_every == 0 or done == cfg.steps or stop:
            seconds = time.perf_counter() - tic
            record = {"step": done, "lr": learning_rate(step, cfg.optim), "time": round(elapsed, 3)}
            record["sec_per_step"] = seconds / len(window)
            record |= {k: float(np.mean([w[k] for w in window])) for k in window[0]}
            if gate_window:
                mean = np.mean(gate_window, axis=0, dtype=np.float64)  # (M, 2)
                record |= {"most_blocks": net.most_names, "most_alpha_s": mean[:, 0].round(4).tolist()}
                record["most_alpha_t"] = mean[:, 1].round(4).tolist()
                gate_window = []
            if info.is_main:
                append_jsonl(log_path, record)
                bar.set_postfix(loss=f"{record['loss']:.4f}")
            window, tic = [], time.perf_counter()
        if info.is_main and cfg.sample_every > 0 and done % cfg.sample_every == 0:
            sampler_net = build_net(cfg, info.device).eval()
            ema.copy_to(sampler_net)
            _save_sample_png(sampler_net, cfg, images, out_dir / "samples" / f"step_{done:07d}.png")
            if gate_plot:
                _save_gate_png(net, gate_plot, done, out_dir / "samples" / f"gates_{done:07d}.png")
                gate_plot = []
        if done % cfg.checkpoint_every == 0 or done == cfg.steps or stop:
            if info.is_main:
                state = checkpoint_state(cfg, done, net, ema, optimizer, elapsed)
                save_checkpoint(out_dir / "checkpoints" / f"step_{done:07d}.pt", state, cfg.keep_checkpoints)
            barrier()
        if stop:
            if info.is_main:
                bar.write(f"stopping at step {done}: wall-clock budget of {cfg.max_minutes} min used")
            break
    bar.close()
    return record


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
    """Arguments of `u4d train-diffusion CONFIG stage=stage1|stage2|baseline [key=value ..] [--resume] [--out]`."""
    add_run_arguments(parser, "configs/u4d/cpu.yaml", "stage=stage1 steps=100 (stage=stage1|stage2|baseline)")


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


def main(argv: list[str] | None = None) -> int:
    """`python -m u4d_aug.train CONFIG ...`: the same as `u4d train-diffusion`, handy under torchrun."""
    parser = argparse.ArgumentParser(prog="python -m u4d_aug.train", description=run_train_diffusion.__doc__)
    add_train_diffusion_arguments(parser)
    return exit_code_of(lambda args: run_train_diffusion(parser.parse_args(args)), argv)


if __name__ == "__main__":
    sys.exit(main())
