"""Segmentation training loop (`u4d seg-train CONFIG [key=value ...] [--resume [CKPT]] [--out DIR]`).

Reads top to bottom like nanoGPT's train.py, on the run layer (`u4d_aug.run`: output folder, resolved config, log,
checkpoints, clock): set-up, data, model, optimiser, then one loop that takes a batch (`segmentation.batches`),
computes the loss with the step function of the configured mode (`supervised_step`, or its sibling
`segmentation.semi.semi_step`: LaserMix mean teacher on labeled + unlabeled scans, after semi.burn_in_steps
supervised steps), steps AdamW at the warm-up + cosine learning rate of that step (`segmentation.optimizer`),
updates the teacher (mode "semi"), evaluates, logs and checkpoints.

Exact resume: the scans of step s, their point subsets and augmentations depend only on (seed, step, slot
in the batch), and the global torch RNG (dropout) is re-seeded from (seed, step, rank) before every step,
so a run resumed from the checkpoint of step s ends with the same weights as an uninterrupted one (same
device, same world size). Checkpoints (kind "u4d-seg-checkpoint") hold the config, step, model, optimiser,
schedule, EMA (the teacher in mode "semi", None when supervised) and RNG states, and are written atomically by
rank 0; those written before the run layer name their kind under "format" and still resume. In mode "semi" the
teacher is the model evaluated and saved as model.pt.

Outputs in OUT (cfg.out_dir): config.yaml, log.jsonl (train records every log_every steps, eval records),
hosts.jsonl (the machine of each start), learning_curve.png, reliability.png, checkpoints/step_XXXXXXX.pt,
burn_in.pt (the step-semi.burn_in_steps state that `u4d experiment` shares), model.pt (final weights + config +
metrics), metrics.json (final evaluation).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader
from tqdm.auto import tqdm

from segmentation.batches import TrainBatches, train_class_counts, train_scans, val_scans
from segmentation.config import SegTrainConfig, class_names
from segmentation.evaluate import evaluate_val, sync_buffers
from segmentation.losses import class_weights, segmentation_loss, voxel_targets
from segmentation.mean_teacher import make_teacher, teacher_mode
from segmentation.models import build_model
from segmentation.optimizer import learning_rate, make_optimizer
from segmentation.plots import plot_learning_curve, plot_reliability
from segmentation.semi import in_burn_in, semi_step, unlabeled_stream, update_teacher
from u4d_aug.config import add_run_arguments, config_to_dict, load_config
from u4d_aug.data.datasets import NuscenesScanDataset, ScanDataset
from u4d_aug.distributed import DistInfo, all_reduce_mean, barrier, cleanup, init_distributed
from u4d_aug.errors import InputError
from u4d_aug.io import append_jsonl, atomic_torch_save, atomic_write_json, read_jsonl
from u4d_aug.memory import check_net_fits
from u4d_aug.progress import progress_bar
from u4d_aug.run import (
    LOG_NAME,
    Clock,
    begin_run,
    checkpoint_state,
    open_run,
    restore,
    save_checkpoint,
)
from u4d_aug.runlock import run_lock
from u4d_aug.seeding import derived_seed
from u4d_aug.validate import check_finite_loss

logger = logging.getLogger(__name__)

CHECKPOINT_KIND = "u4d-seg-checkpoint"  # u4d_aug.weights.SEGMENTATION_KIND
# the logged losses (the last 3: mode "semi" only), then the evaluation metrics
CURVE_KEYS: tuple[str, ...] = ("loss", "loss_ce", "loss_lovasz", "loss_sup", "loss_mix", "loss_mt")
CURVE_KEYS += ("val_miou", "val_ece_per_scan", "val_ece_pooled")
Scans = ScanDataset | NuscenesScanDataset
_STEP = 3  # seed domain of the dropout of a step (segmentation.batches uses 1, 2; segmentation.semi 4-6)


def train(cfg: SegTrainConfig, resume: str | Path | None = None, progress: bool = True) -> dict:
    """Train as configured; returns the final evaluation summary (empty without val scans).

    Rank 0 holds the run lock of OUT (`u4d_aug.runlock`) for the whole run: a second run on OUT is refused.
    """
    check_net_fits(lambda: build_model(cfg.model), "the net of model.*", "reduce model.width or the other sizes")
    info = init_distributed(cfg.device)
    with run_lock(cfg.out_dir, enabled=info.is_main):
        return train_locked(cfg, info, resume, progress)


def train_locked(cfg: SegTrainConfig, info: DistInfo, resume: str | Path | None, progress: bool) -> dict:
    """The run of `train` once OUT is locked: set-up, loop, evaluate, checkpoint, done."""
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out_dir)
    start = open_run(out, resume, info.is_main, CHECKPOINT_KIND, "u4d seg-train")
    check_processes(cfg, info)
    scans, val = train_scans(cfg, info), val_scans(cfg)
    unlabeled = unlabeled_stream(cfg) if cfg.mode == "semi" else None
    # CE class weights from the labelled training points (every rank counts the same scans)
    class_weight = class_weights(train_class_counts(scans), cfg.loss) if cfg.loss.class_weighting != "none" else None

    torch.manual_seed(cfg.seed)  # the same initial weights on every rank (DDP also broadcasts rank 0's)
    model = build_model(cfg.model).to(info.device)
    # mode "semi": the mean teacher, an EMA of the student; it is the model evaluated and saved
    teacher = teacher_mode(make_teacher(model), cfg.semi.bn_mode) if cfg.mode == "semi" else None
    evaluated = teacher if teacher is not None else model
    optimizer = make_optimizer(model, cfg.optim)
    restore(start, cfg, model, optimizer, teacher, ignore=("out_dir",))
    summary = (start.checkpoint or {}).get("metrics")  # the last evaluation
    begin_run(out, cfg, start, info)
    if info.is_main and class_weight is not None and start.step == 0:
        append_jsonl(out / LOG_NAME, {"step": 0, "class_weight": dict(zip(class_names(cfg), class_weight.tolist()))})
    ddp_model = DistributedDataParallel(model) if info.world_size > 1 else model

    loader = step_loader(TrainBatches(scans, cfg, info.rank, info.world_size, unlabeled), start.step, cfg, info)
    bar = progress_bar(total=cfg.optim.steps, initial=start.step, desc="seg-train", enabled=(progress and info.is_main))
    clock, window, done = Clock(cfg.max_minutes, start.elapsed), LogWindow(), start.step
    model.train()
    for batch in loader:  # after the body of step s, done = s + 1 steps are finished
        step = int(batch["step"])
        lr = learning_rate(step, cfg.optim, clock.fraction() if cfg.optim.anneal_to == "budget" else 0.0)
        losses, grad_norm = optimize(step, lr, batch, (ddp_model, model, teacher), optimizer, cfg, info, class_weight)
        done = step + 1

        window.add(losses, grad_norm)
        bar.update(1)
        bar.set_postfix(loss=f"{losses['loss'].item():.3f}", lr=f"{lr:.2e}")
        elapsed, out_of_time = clock.read()
        last = done == cfg.optim.steps or out_of_time
        if done % cfg.log_every == 0 or last:
            record = {"step": done, "lr": lr, "time": round(elapsed, 3)} | window.means(info.device)
            if info.is_main:
                append_jsonl(out / LOG_NAME, record)
            window = LogWindow()
        if done % cfg.eval_every == 0 or last:
            summary = evaluate_and_log(evaluated, cfg, val, info, done, elapsed, bar) or summary
        periodic = done % cfg.checkpoint_every == 0 or last
        burn_in_end = 0 < cfg.semi.burn_in_steps == done  # also in mode "supervised": the same first steps
        if periodic or burn_in_end:
            if info.is_main:
                extra = extra_state(cfg, done, lr, summary, class_weight)
                state = checkpoint_state(CHECKPOINT_KIND, cfg, done, elapsed, model, optimizer, teacher, **extra)
                if periodic:
                    save_checkpoint(out, state, cfg.keep_checkpoints)
                if burn_in_end:  # kept whatever the rotation: `u4d experiment` starts the other arms from it
                    atomic_torch_save(out / "burn_in.pt", state)
            barrier()
        if out_of_time:
            if info.is_main:
                bar.write(f"stopping at step {done}: wall-clock budget of {cfg.max_minutes} min used")
            break
    bar.close()

    if info.is_main:  # weights + config for seg-eval / seg-predict (the teacher in mode "semi"), the last evaluation
        atomic_torch_save(out / "model.pt", final_weights(cfg, done, evaluated, summary))
        atomic_write_json(out / "metrics.json", {"step": done, **(summary or {})})
    barrier()
    return summary or {}


# ---------------------------------------------------------------------------------------------------- helpers


def step_loader(batches: TrainBatches, start: int, cfg: SegTrainConfig, info: DistInfo) -> DataLoader:
    """The batches of steps start, start + 1, ... (the DataLoader draws with its own generator, not the global RNG)."""
    return DataLoader(
        batches, batch_size=None, sampler=range(start, cfg.optim.steps), num_workers=cfg.num_workers,
        pin_memory=info.device.type == "cuda", generator=torch.Generator().manual_seed(cfg.seed),
    )  # fmt: skip


def step_losses(
    model: nn.Module,
    teacher: nn.Module | None,
    batch: dict,
    cfg: SegTrainConfig,
    device: torch.device,
    class_weight: torch.Tensor | None,
) -> dict:
    """The losses of one step in the configured mode: supervised (also the burn-in of mode "semi"), or semi."""
    if cfg.mode == "supervised" or (cfg.mode == "semi" and in_burn_in(cfg.semi, int(batch["step"]))):
        return supervised_step(model, batch, cfg, device, class_weight)
    elif cfg.mode == "semi":
        if teacher is None:
            raise ValueError("mode 'semi' needs the mean teacher (segmentation.mean_teacher.make_teacher); got None")
        return semi_step(model, teacher, batch, cfg, device, class_weight)
    raise ValueError(f"mode must be 'supervised' or 'semi'; got {cfg.mode!r}")


def extra_state(
    cfg: SegTrainConfig, step: int, lr: float, summary: dict | None, class_weight: torch.Tensor | None
) -> dict:
    """What a seg-train checkpoint holds beside the run layer's: the last evaluation, schedule, class names, CE class
    weights."""
    return {
        "metrics": summary,
        "scheduler": {"name": "warmup_cosine", "step": step, "lr": lr},
        "class_names": class_names(cfg),
        "class_weight": class_weight,
    }


def optimize(
    step: int,
    lr: float,
    batch: dict,
    models: tuple[nn.Module, nn.Module, nn.Module | None],
    optimizer: torch.optim.Optimizer,
    cfg: SegTrainConfig,
    info: DistInfo,
    class_weight: torch.Tensor | None,
) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
    """Step `step` of the loop: seed its dropout, loss of the mode, backward, clip, AdamW at `lr`, then the teacher's
    EMA update; models = (the DDP-wrapped student, the student, the teacher or None). Returns (losses, grad norm)."""
    ddp_model, model, teacher = models
    for group in optimizer.param_groups:
        group["lr"] = lr
    torch.manual_seed(derived_seed(cfg.seed, _STEP, step, info.rank))  # dropout of this step only
    losses = step_losses(ddp_model, teacher, batch, cfg, info.device, class_weight)
    check_finite_loss(losses["loss"], step + 1)
    optimizer.zero_grad(set_to_none=True)
    losses["loss"].backward()
    grad_norm = nn.utils.clip_grad_norm_(model.parameters(), cfg.optim.grad_clip) if cfg.optim.grad_clip else None
    check_finite_loss(losses["loss"], step + 1, gradient_norm(model, grad_norm))  # before NaN weights follow
    optimizer.step()
    if teacher is not None:
        update_teacher(teacher, model, cfg.semi, step)
    return losses, grad_norm


def supervised_step(
    model: nn.Module, batch: dict, cfg: SegTrainConfig, device: torch.device, class_weight: torch.Tensor | None = None
) -> dict:
    """Losses of one labeled batch: {"loss", "loss_ce", ["loss_lovasz"]} (the loop backpropagates "loss")."""
    points = [p.to(device, non_blocking=True) for p in batch["points"]]
    target = torch.cat(batch["labels"]).to(device)  # (sum N_b,)
    ignore = cfg.data.label_set.ignore_index
    if cfg.loss.level == "voxel":
        out = model(points, voxel_output=True)  # logits (M, K) of the occupied voxels
        logits, target = out.logits, voxel_targets(target, out.inverse, out.logits.shape[0], ignore)
    else:
        logits = model(points)  # (sum N_b, K)
    return segmentation_loss(logits, target, cfg.loss, ignore, class_weight)


def check_processes(cfg: SegTrainConfig, info: DistInfo) -> None:
    """The run fits its data and processes: the net's classes are the scans' train ids, every rank gets a scan."""
    labels = cfg.data.label_set
    if cfg.model.num_classes != labels.num_classes:
        raise InputError(
            f"model.num_classes={cfg.model.num_classes}: the {cfg.data.format} scans carry {labels.num_classes} "
            f"train ids; set model.num_classes={labels.num_classes}"
        )
    if cfg.optim.batch_size < info.world_size:
        raise InputError(
            f"optim.batch_size={cfg.optim.batch_size} is smaller than the {info.world_size} processes; "
            "every rank needs at least one scan per step"
        )


def gradient_norm(model: nn.Module, clipped: torch.Tensor | None) -> torch.Tensor:
    """The global gradient norm of the step: the clipped one, else taken here for the finite check only."""
    if clipped is not None:
        return clipped
    return nn.utils.get_total_norm([p.grad for p in model.parameters() if p.grad is not None])


class LogWindow:
    """Sums of the losses (and clipped grad norms) of the steps since the last train record, as float32 tensors."""

    def __init__(self) -> None:
        self.sums: dict[str, torch.Tensor] = {}
        self.count = 0

    def add(self, losses: dict[str, torch.Tensor], grad_norm: torch.Tensor | None) -> None:
        values = losses if grad_norm is None else {**losses, "grad_norm": grad_norm}
        for key, value in values.items():
            self.sums[key] = self.sums.get(key, 0.0) + value.detach().float()
        self.count += 1

    def means(self, device: torch.device) -> dict[str, float]:
        """Mean of each value over the window's steps and over ranks (a collective)."""
        return {k: float(all_reduce_mean(torch.as_tensor(v / self.count, device=device))) for k, v in self.sums.items()}


def evaluate_and_log(
    evaluated: nn.Module, cfg: SegTrainConfig, val: Scans | None, info: DistInfo, step: int, elapsed: float, bar: tqdm
) -> dict | None:
    """The periodic evaluation of `step` on the val scans (all ranks): its summary (None without val scans), logged
    with the reliability diagram and the learning curve by rank 0."""
    sync_buffers(evaluated)
    summary, bins = evaluate_val(evaluated, cfg, val, info)
    if cfg.mode == "semi":
        teacher_mode(evaluated, cfg.semi.bn_mode)  # evaluation left the teacher in train mode
    out = Path(cfg.out_dir)
    if summary is not None and info.is_main:
        record = {"step": step, "time": round(elapsed, 3), "val_miou": summary["miou"]}
        record |= {"val_ece_per_scan": summary["ece_per_scan"], "val_ece_pooled": summary["ece_pooled"]}
        append_jsonl(out / LOG_NAME, record | {"val_iou": summary["iou"]})
        plot_reliability(bins, out / "reliability.png", title=f"step {step}")
        bar.write(
            f"step {step}: val mIoU {_pct(summary['miou'])}, ECE per scan "
            f"{_pct(summary['ece_per_scan'])}, pooled {_pct(summary['ece_pooled'])}"
        )
    if info.is_main:
        plot_learning_curve(read_jsonl(out / LOG_NAME), out / "learning_curve.png", "step", CURVE_KEYS)
    return summary


def final_weights(cfg: SegTrainConfig, step: int, evaluated: nn.Module, summary: dict | None) -> dict:
    """OUT/model.pt: the evaluated net's weights (the teacher in mode "semi") with config, step and metrics."""
    return {
        "kind": CHECKPOINT_KIND,
        "config": config_to_dict(cfg),
        "step": step,
        "model": evaluated.state_dict(),
        "metrics": summary,
        "class_names": class_names(cfg),
    }


def _pct(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.2f}%"


# ------------------------------------------------------------------------------------------------------- CLI


def add_seg_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d seg-train CONFIG [key=value ...] [--resume [CKPT]] [--out DIR]`."""
    add_run_arguments(parser, "configs/seg/cpu_minkunet.yaml", "optim.steps=100 model.width=0.5")


def run_seg_train(args: argparse.Namespace) -> int:
    """`u4d seg-train`: supervised or semi-supervised training (torchrun for several processes)."""
    cfg = load_config(SegTrainConfig, args.config, args.overrides)
    if args.out is not None:
        cfg.out_dir = args.out
    try:
        train(cfg, resume=args.resume, progress=not args.no_progress)
    finally:
        cleanup()
    return 0
