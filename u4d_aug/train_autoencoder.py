"""Training of the range-image autoencoder of latent diffusion: `u4d train-autoencoder CONFIG [key=value ..]`.

The latent generators (LiDM, Ran et al. 2024) diffuse in the latent of a `RangeAutoencoder`, so the autoencoder
learns both kinds of image they generate: full scans x0 and, for U4D's stage 1, the uncertain region x0_u alone
(the first round(uncertain_share · B) items of each batch). The loop reads top to bottom on the run layer
(`u4d_aug.run`); a step's scans, crops and noise depend only on (seed, step, rank), so a resumed run ends as an
uninterrupted one. At the end the latent's per-channel statistics are set from training scans and OUT/autoencoder.pt
(weights + config, what a latent diffusion run's `autoencoder` key names) and OUT/reconstruction.png are written.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path

import torch
from torch import Tensor, nn

from u4d_aug.autoencoder_stage import (
    WEIGHTS_NAME,
    AutoencoderTrainConfig,
    build_autoencoder,
    save_autoencoder,
)
from u4d_aug.batches import RangeImages, batch_indices, crop_batch, crop_loss_weight, make_batch
from u4d_aug.config import add_run_arguments, load_config
from u4d_aug.diffusion import DiffusionConfig
from u4d_aug.distributed import DistInfo, all_reduce_mean, barrier, cleanup, init_distributed
from u4d_aug.io import append_jsonl
from u4d_aug.nn.autoencoder import RangeAutoencoder
from u4d_aug.progress import progress_bar
from u4d_aug.run import LOG_NAME, Clock, begin_run, checkpoint_state, open_run, restore, save_checkpoint
from u4d_aug.runlock import run_lock
from u4d_aug.seeding import derived_seed
from u4d_aug.stage import DiffusionTrainConfig
from u4d_aug.train import learning_rate
from u4d_aug.validate import check_finite_loss

logger = logging.getLogger(__name__)

CHECKPOINT_KIND = "u4d-autoencoder-checkpoint"
_CROP = 3  # stream of derived_seed (batches.py uses 1 and 2)


def image_source(cfg: AutoencoderTrainConfig) -> RangeImages:
    """The range images of cfg's scans as train-diffusion reads them: x0, and x0_u / m_u when uncertain_share > 0."""
    stage = "u4d" if cfg.uncertain_share > 0 else "baseline"
    view = DiffusionTrainConfig(
        data_root=cfg.data_root, data_format=cfg.data_format, nuscenes_version=cfg.nuscenes_version,
        sequences=cfg.sequences, probs_root=cfg.probs_root, sensor=cfg.sensor, height=cfg.height, width=cfg.width,
        row_mode=cfg.row_mode, uncertainty=cfg.uncertainty, diffusion=DiffusionConfig(stage=stage, min_snr_gamma=None),
        cache_images=cfg.cache_images, batch_size=max(2, cfg.batch_size),
    )  # fmt: skip
    return RangeImages(view)


def training_images(
    images: RangeImages, cfg: AutoencoderTrainConfig, step: int, rank: int, device: torch.device
) -> tuple[Tensor, torch.Generator]:
    """This rank's images (B, 2, H, crop) of `step`: the first round(uncertain_share · B) are x0_u, the rest x0, each
    an azimuth crop at a random multiple of the latent factor; and the (seed, step, rank) generator of the noise."""
    generator = torch.Generator().manual_seed(derived_seed(cfg.seed, _CROP, step, rank))
    indices = batch_indices(step, rank, len(images), cfg.batch_size, cfg.seed)
    batch = make_batch(images, indices, generator, device)
    uncertain = round(cfg.uncertain_share * cfg.batch_size)
    x = batch["x0"] if uncertain == 0 else torch.cat([batch["x0_u"][:uncertain], batch["x0"][uncertain:]])
    if cfg.crop_width:
        factor = cfg.ae.factor
        offsets = factor * torch.randint(0, cfg.width // factor, (len(indices),), generator=generator)
        x = crop_batch({"x0": x}, offsets, cfg.crop_width)["x0"]
    return x, generator


def train(cfg: AutoencoderTrainConfig, resume: str | Path | None = None, progress: bool = True) -> dict:
    """Train the autoencoder; returns the last logged record. Writes OUT/{config.yaml, log.jsonl, checkpoints/,
    autoencoder.pt, reconstruction.png}; rank 0 holds OUT's run lock."""
    info: DistInfo = init_distributed(cfg.device)
    with run_lock(cfg.out, enabled=info.is_main):
        return _train_locked(cfg, info, resume, progress)


def _train_locked(cfg: AutoencoderTrainConfig, info: DistInfo, resume: str | Path | None, progress: bool) -> dict:
    out = Path(cfg.out)
    start = open_run(out, resume, info.is_main, CHECKPOINT_KIND, "u4d train-autoencoder")
    images = image_source(cfg)
    net = build_autoencoder(cfg.ae, cfg.seed).to(info.device)
    optim = cfg.optim
    optimizer = torch.optim.AdamW(net.parameters(), lr=optim.lr, betas=optim.betas, weight_decay=optim.weight_decay)
    restore(start, cfg, net, optimizer, ignore=("out",))
    begin_run(out, cfg, start, info)
    model: nn.Module = net
    if info.world_size > 1:
        model = nn.parallel.DistributedDataParallel(
            net, device_ids=[info.device.index] if info.device.type == "cuda" else None
        )
    weight = column_weight(cfg, info.device)

    record: dict = {}
    window: list[dict] = []
    clock, tic, stop = Clock(cfg.max_minutes, start.elapsed), time.perf_counter(), False
    bar = progress_bar(range(start.step, cfg.steps), initial=start.step, total=cfg.steps,
                       enabled=progress and info.is_main, desc="train autoencoder")  # fmt: skip
    for step in bar:
        x, generator = training_images(images, cfg, step, info.rank, info.device)
        lr = learning_rate(step, optim, cfg.steps, clock.fraction() if optim.schedule == "cosine" else 0.0)
        for group in optimizer.param_groups:
            group["lr"] = lr

        losses = model(x, generator, cfg.kl_weight, cfg.mask_weight, weight, tuple(cfg.value_weights))
        check_finite_loss(losses["loss"], step + 1)
        optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        grad_norm = nn.utils.clip_grad_norm_(net.parameters(), optim.grad_clip if optim.grad_clip > 0 else float("inf"))
        check_finite_loss(losses["loss"], step + 1, grad_norm)
        optimizer.step()

        window.append(
            {k: float(all_reduce_mean(v.detach())) for k, v in losses.items()} | {"grad_norm": float(grad_norm)}
        )
        done = step + 1
        elapsed, stop = clock.read()
        if done % cfg.log_every == 0 or done == cfg.steps or stop:
            record = {"step": done, "lr": lr, "time": round(elapsed, 3),
                      "sec_per_step": (time.perf_counter() - tic) / len(window)}  # fmt: skip
            record |= {k: sum(w[k] for w in window) / len(window) for k in window[0]}
            if info.is_main:
                append_jsonl(out / LOG_NAME, record)
                bar.set_postfix(l1=f"{record['l1']:.4f}")
            window, tic = [], time.perf_counter()
        if done % cfg.checkpoint_every == 0 or done == cfg.steps or stop:
            if info.is_main:
                save_checkpoint(
                    out, checkpoint_state(CHECKPOINT_KIND, cfg, done, elapsed, net, optimizer), cfg.keep_checkpoints
                )
            barrier()
        if stop:
            if info.is_main:
                bar.write(f"stopping at step {done}: wall-clock budget of {cfg.max_minutes} min used")
            break
    bar.close()
    if info.is_main and (not record or record["step"] == cfg.steps or stop):  # a budget-stopped run is done too
        finish(net.eval(), cfg, images, out, info.device)
    barrier()
    return record


def column_weight(cfg: AutoencoderTrainConfig, device: torch.device) -> Tensor | None:
    """(crop_width,) weights of the loss per column: 0 on the crop's margins, else 1 (None: no crop or no margin);
    `batches.crop_loss_weight` of the crop."""
    return crop_loss_weight(cfg, device) if cfg.crop_width else None  # type: ignore[arg-type]


def statistic_images(images: RangeImages, cfg: AutoencoderTrainConfig) -> Tensor:
    """(N, 2, H, W) full-width images of `stats_scans` evenly spaced training scans, x0 and x0_u in the training mix."""
    step = max(1, len(images) // cfg.stats_scans)
    picked = list(range(0, len(images), step))[: cfg.stats_scans]
    uncertain = round(cfg.uncertain_share * len(picked))
    generator = torch.Generator().manual_seed(cfg.seed)
    items = [images.__getitem__(i, generator) for i in picked]
    return torch.stack([item["x0_u" if n < uncertain else "x0"] for n, item in enumerate(items)])


@torch.no_grad()
def finish(
    net: RangeAutoencoder, cfg: AutoencoderTrainConfig, images: RangeImages, out: Path, device: torch.device
) -> None:
    """Set the latent statistics from training scans, write OUT/autoencoder.pt and OUT/reconstruction.png."""
    sample = statistic_images(images, cfg)
    net.set_latent_statistics(torch.cat([net.encode(chunk.to(device))[0] for chunk in sample.split(8)]))
    save_autoencoder(out / WEIGHTS_NAME, net, cfg)
    x = images[0]["x0"][None].to(device)
    save_reconstruction_png(x, net.from_latent(net.to_latent(x)), out / "reconstruction.png")


def save_reconstruction_png(x: Tensor, recon: Tensor, path: Path) -> None:
    """The depth of one scan's range image and of its reconstruction, one above the other."""
    import matplotlib.pyplot as plt

    from u4d_aug.viz import draw_range_image, save_figure

    fig, axes = plt.subplots(2, 1, figsize=(12, 3.2))
    draw_range_image(axes[0], x[0, 0].cpu().numpy(), "depth", vmin=-1, vmax=1, unit="log-depth [-1, 1]")
    draw_range_image(axes[1], recon[0, 0].cpu().numpy(), "reconstructed", vmin=-1, vmax=1, unit="log-depth [-1, 1]")
    save_figure(fig, path)


def add_train_autoencoder_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d train-autoencoder CONFIG [key=value ..] [--resume] [--out]`."""
    add_run_arguments(parser, "configs/u4d/autoencoder_hdl64.yaml", "steps=100 uncertain_share=0")


def run_train_autoencoder(args: argparse.Namespace) -> int:
    """`u4d train-autoencoder`: train the range-image autoencoder of the latent generators."""
    cfg = load_config(AutoencoderTrainConfig, args.config, list(args.overrides))
    if args.out is not None:
        cfg = dataclasses.replace(cfg, out=str(args.out))
    try:
        train(cfg, resume=args.resume, progress=not args.no_progress)
    finally:
        cleanup()
    return 0
