"""Segmentation training loop (`u4d seg-train CONFIG [key=value ...] [--resume [CKPT]] [--out DIR]`).

Reads top to bottom like nanoGPT's train.py: set-up, data, model, optimiser, then one loop that takes a batch,
computes the loss with the step function of the configured mode (`supervised_step`, or its sibling
`segmentation.semi.semi_step`: LaserMix mean teacher on labeled + unlabeled scans, after semi.burn_in_steps
supervised steps), steps AdamW at the warm-up + cosine learning rate of that step, updates the teacher (mode
"semi"), evaluates, logs and checkpoints.

Exact resume: the scans of step s, their point subsets and augmentations depend only on (seed, step, slot
in the batch), and the global torch RNG (dropout) is re-seeded from (seed, step, rank) before every step,
so a run resumed from the checkpoint of step s ends with the same weights as an uninterrupted one (same
device, same world size). Checkpoints hold the config, step, model, optimiser, schedule, EMA (the teacher in
mode "semi", None when supervised) and RNG states, and are written atomically by rank 0. In mode "semi" the
teacher is the model evaluated and saved as model.pt.

Outputs in OUT (cfg.out_dir): config.yaml, log.jsonl (train records every log_every steps, eval records),
learning_curve.png, reliability.png, checkpoints/step_XXXXXXX.pt, model.pt (final weights + config + metrics),
metrics.json (final evaluation).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset

from segmentation.config import SegOptimConfig, SegTrainConfig
from segmentation.data import augment, load_or_make_split, paste_instances, training_subset
from segmentation.evaluate import accumulate, evenly_spaced, summary_of
from segmentation.losses import class_weights, segmentation_loss, voxel_targets
from segmentation.mean_teacher import make_teacher, teacher_mode
from segmentation.models import build_model
from segmentation.plots import plot_learning_curve, plot_reliability
from segmentation.predict import load_checkpoint
from segmentation.semi import (
    UnlabeledStream,
    in_burn_in,
    load_unlabeled,
    semi_step,
    unlabeled_stream,
    update_teacher,
)
from u4d_aug.cmdline import parse_command_line
from u4d_aug.config import add_run_arguments, config_to_dict, load_config, save_config, without_removed_keys
from u4d_aug.data.datasets import NuscenesScanDataset, ScanDataset, open_scans
from u4d_aug.distributed import (
    DistInfo,
    all_reduce_mean,
    barrier,
    budget_fraction,
    budget_used,
    cleanup,
    init_distributed,
)
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.host import host_info
from u4d_aug.io import append_jsonl, atomic_torch_save, atomic_write_json, atomic_write_text, read_jsonl
from u4d_aug.progress import progress_bar
from u4d_aug.runfolder import prepare, resume_point
from u4d_aug.runlock import run_lock
from u4d_aug.seeding import derived_seed
from u4d_aug.validate import check_finite_loss

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "u4d-seg-checkpoint"
CURVE_KEYS = ("loss", "loss_ce", "loss_lovasz", "loss_sup", "loss_mix", "loss_mt")  # mode "semi": the last 3
CURVE_KEYS += ("val_miou", "val_ece_per_scan", "val_ece_pooled")
# seed domains, so that the streams of epochs, scans and dropout never share a seed
_EPOCH, _SCAN, _STEP = 1, 2, 3


# ---------------------------------------------------------------------------------------------------- helpers


def batch_indices(step: int, num_scans: int, batch_size: int, seed: int) -> list[int]:
    """Scan indices of the global batch of `step`: consecutive slices of one seeded permutation per epoch."""
    positions = range(step * batch_size, (step + 1) * batch_size)
    permutations: dict[int, torch.Tensor] = {}
    out = []
    for position in positions:
        epoch, within = divmod(position, num_scans)
        if epoch not in permutations:
            generator = torch.Generator().manual_seed(derived_seed(seed, _EPOCH, epoch))
            permutations[epoch] = torch.randperm(num_scans, generator=generator)
        out.append(int(permutations[epoch][within]))
    return out


def learning_rate(step: int, cfg: SegOptimConfig, time_fraction: float = 0.0) -> float:
    """Linear warm-up over warmup_steps, then cosine from lr down to min_lr_ratio * lr (nanoGPT get_lr).

    time_fraction (share of the wall-clock budget used, optim.anneal_to "budget") moves the cosine on when the
    budget runs out before the steps do: progress = max(step progress, time_fraction).
    """
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    decay_steps = max(1, cfg.steps - cfg.warmup_steps)
    progress = min(1.0, max((step - cfg.warmup_steps) / decay_steps, time_fraction))
    min_lr = cfg.lr * cfg.min_lr_ratio
    return min_lr + 0.5 * (1.0 + math.cos(math.pi * progress)) * (cfg.lr - min_lr)


def make_optimizer(model: nn.Module, cfg: SegOptimConfig) -> torch.optim.AdamW:
    """AdamW with weight decay on >= 2-d weights only (convs, linears), not on biases and norms (nanoGPT)."""
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [
        {"params": [p for p in params if p.dim() >= 2], "weight_decay": cfg.weight_decay},
        {"params": [p for p in params if p.dim() < 2], "weight_decay": 0.0},
    ]
    return torch.optim.AdamW(groups, lr=cfg.lr, betas=cfg.betas)


class TrainBatches(Dataset):
    """Item `step` = this rank's share of the global batch of that step: loaded, subsampled, augmented scans.

    Slot j of the global batch goes to rank j % world_size; its randomness is seeded by (seed, step, j), so
    the global batch does not depend on the number of ranks or DataLoader workers. With an unlabeled stream
    (mode "semi") the item also holds as many unlabeled scans, slot for slot.
    """

    def __init__(
        self,
        scans: ScanDataset | NuscenesScanDataset,
        cfg: SegTrainConfig,
        rank: int,
        world_size: int,
        unlabeled: UnlabeledStream | None = None,
    ) -> None:
        self.scans, self.cfg, self.rank, self.world_size = scans, cfg, rank, world_size
        self.unlabeled = unlabeled
        names = list(cfg.data.label_set.classes)  # SegTrainConfig has checked the paste class names
        self.paste_ids = torch.tensor([names.index(name) for name in cfg.augment.paste_classes], dtype=torch.int64)

    def __len__(self) -> int:
        return self.cfg.optim.steps

    def __getitem__(self, step: int) -> dict:
        cfg = self.cfg
        indices = batch_indices(step, len(self.scans), cfg.optim.batch_size, cfg.seed)
        slots = range(self.rank, cfg.optim.batch_size, self.world_size)
        points, labels = [], []
        for slot in slots:
            item = self.scans[indices[slot]]
            generator = torch.Generator().manual_seed(derived_seed(cfg.seed, _SCAN, step, slot))
            scan = torch.from_numpy(item["points"])  # (N, 4)
            target = torch.from_numpy(item["labels"])  # (N,) train ids
            keep = training_subset(scan, cfg.data.sector_deg, cfg.data.max_points, generator)
            scan, target = scan[keep], target[keep]
            if cfg.augment.paste_prob > 0 and float(torch.rand((), generator=generator)) < cfg.augment.paste_prob:
                source = self.scans[int(torch.randint(len(self.scans), (), generator=generator))]
                scan, target = paste_instances(
                    scan,
                    target,
                    torch.from_numpy(source["points"]),
                    torch.from_numpy(source["labels"]),
                    self.paste_ids,
                    cfg.augment.paste_copies,
                    generator,
                )
            points.append(augment(scan, generator, cfg.augment))
            labels.append(target)
        batch = {"step": step, "slots": list(slots), "points": points, "labels": labels}
        if self.unlabeled is not None and not in_burn_in(cfg.semi, step):
            batch["unlabeled"], unlabeled_labels = load_unlabeled(self.unlabeled, cfg, step, slots)
            if unlabeled_labels is not None:
                batch["unlabeled_labels"] = unlabeled_labels
        return batch


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


def train_class_counts(scans: ScanDataset | NuscenesScanDataset) -> torch.Tensor:
    """(K,) labelled points per train id over the training scans (labels only; the ignore id dropped)."""
    labels = scans.label_set
    counts = np.zeros(labels.num_classes, dtype=np.int64)
    for index in range(len(scans.entries)):
        train_ids = scans.train_ids(index)
        counts += np.bincount(train_ids, minlength=labels.ignore_index + 1)[: len(counts)]
    return torch.from_numpy(counts)


def data_scans(cfg: SegTrainConfig, sequences, labeled_only: bool) -> ScanDataset | NuscenesScanDataset:
    """The scans of `sequences` under data.root, read in data.format."""
    data = cfg.data
    return open_scans(data.root, sequences, labeled_only, data.format, data.nuscenes_version)


def train_scans(cfg: SegTrainConfig, info: DistInfo) -> ScanDataset | NuscenesScanDataset:
    """Labeled scans of the train sequences, restricted to the labeled split if label_fraction < 1."""
    scans = data_scans(cfg, cfg.data.train_sequences, labeled_only=True)
    if len(scans) == 0:
        raise InputError(f"{cfg.data.root}: no labeled scan in the train sequences {scans.sequences}")
    if cfg.data.label_fraction < 1.0:
        # rank 0 draws and writes the split file beside the data; the others then read it
        if info.is_main:
            labeled, _ = load_or_make_split(
                cfg.data.root,
                scans.entries,
                cfg.data.label_fraction,
                cfg.data.split_seed,
                cfg.data.split_mode,
            )
        barrier()
        if not info.is_main:
            labeled, _ = load_or_make_split(
                cfg.data.root,
                scans.entries,
                cfg.data.label_fraction,
                cfg.data.split_seed,
                cfg.data.split_mode,
            )
        chosen = set(labeled)
        scans.entries = [entry for entry in scans.entries if entry in chosen]
    return scans


def save_checkpoint(path: Path, state: dict, keep: int) -> None:
    """Write atomically, then delete all but the newest `keep` step_*.pt beside it (0 = keep all)."""
    atomic_torch_save(path, state)
    if keep > 0:
        for old in sorted(path.parent.glob("step_*.pt"))[:-keep]:
            old.unlink(missing_ok=True)


def evaluate_val(
    model: nn.Module, cfg: SegTrainConfig, val_scans: ScanDataset | NuscenesScanDataset | None, info: DistInfo
):
    """Periodic evaluation on the val scans, shared by all ranks: (summary, pooled bins) or (None, None)."""
    if val_scans is None:
        return None, None
    indices = evenly_spaced(len(val_scans), cfg.data.val_max_scans)
    cm, calibration = accumulate(
        model, val_scans, indices, info.device, cfg.model.num_classes, cfg.data.label_set.ignore_index,
        info.rank, info.world_size,
    )  # fmt: skip
    return summary_of(cm, calibration, class_names(cfg)), calibration.pooled


def sync_buffers(model: nn.Module) -> None:
    """Copy rank 0's buffers (BatchNorm statistics) to every rank, so that all ranks evaluate one model."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        for buffer in model.buffers():
            torch.distributed.broadcast(buffer, src=0)


def class_names(cfg: SegTrainConfig) -> list[str]:
    """Train-id names of the net's classes (the data's label set)."""
    names = list(cfg.data.label_set.classes[: cfg.model.num_classes])
    return names + [f"class_{k}" for k in range(len(names), cfg.model.num_classes)]


def rewrite_log(path: Path, last_step: int) -> None:
    """On resume: drop log records written after the checkpoint (they will be written again)."""
    if path.is_file():
        records = [r for r in read_jsonl(path) if r.get("step", 0) <= last_step]
        atomic_write_text(path, "".join(json.dumps(r) + "\n" for r in records))


# ------------------------------------------------------------------------------------------------------ loop


def train(cfg: SegTrainConfig, resume: str | Path | None = None, progress: bool = True) -> dict:
    """Train as configured; returns the final evaluation summary (empty without val scans).

    Rank 0 holds the run lock of OUT (`u4d_aug.runlock`) for the whole run: a second run on OUT is refused.
    """
    info = init_distributed(cfg.device)
    with run_lock(cfg.out_dir, enabled=info.is_main):
        return train_locked(cfg, info, resume, progress)


def train_locked(cfg: SegTrainConfig, info: DistInfo, resume: str | Path | None, progress: bool) -> dict:
    """The run of `train` once OUT is locked: set-up, resume point, loop, final outputs."""
    device = info.device
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    out_dir = Path(cfg.out_dir)
    log_path = out_dir / "log.jsonl"
    ckpt_path = resume_point(out_dir, resume)  # None: step 0 (also --resume before the first checkpoint)
    if info.is_main:
        prepare(out_dir, ckpt_path)
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

    # ---- data
    scans = train_scans(cfg, info)
    val_scans = None
    if cfg.data.val_sequences is not None:
        val_scans = data_scans(cfg, cfg.data.val_sequences, labeled_only=True)
        val_scans = val_scans if len(val_scans) else None
    unlabeled = unlabeled_stream(cfg) if cfg.mode == "semi" else None
    # CE class weights from the labelled training points (every rank counts the same scans)
    class_weight = class_weights(train_class_counts(scans), cfg.loss) if cfg.loss.class_weighting != "none" else None

    # ---- model and optimiser (same initial weights on every rank; DDP also broadcasts rank 0's)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model).to(device)
    # mode "semi": the mean teacher, an EMA of the student; it is the model evaluated and saved
    teacher = teacher_mode(make_teacher(model), cfg.semi.bn_mode) if cfg.mode == "semi" else None
    evaluated = teacher if teacher is not None else model
    optimizer = make_optimizer(model, cfg.optim)
    start_step, elapsed_before, last_summary = 0, 0.0, None
    if ckpt_path is not None:
        ckpt = load_checkpoint(ckpt_path)
        if ckpt.get("format") != CHECKPOINT_FORMAT or "optimizer" not in ckpt:
            raise InputError(
                f"{ckpt_path}: not a seg-train training checkpoint (resume from OUT/checkpoints/step_*.pt)"
            )
        _warn_config_changes(ckpt["config"], config_to_dict(cfg), ckpt_path)
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        if teacher is not None:
            if ckpt.get("ema") is None:
                raise InputError(f"{ckpt_path}: has no teacher (ema) weights; it was not written in mode 'semi'")
            teacher.load_state_dict(ckpt["ema"])
        start_step, elapsed_before = int(ckpt["step"]), float(ckpt.get("elapsed", 0.0))
        last_summary = ckpt.get("metrics")
        torch.set_rng_state(ckpt["rng"]["torch"])
        if info.is_main:
            rewrite_log(log_path, start_step)
            logger.info("resuming from %s at step %d", ckpt_path, start_step)
    if info.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, out_dir / "config.yaml")
        # the machine of each start and resume: wall-clock figures read with it (u4d_aug/host.py)
        append_jsonl(out_dir / "hosts.jsonl", {"step": start_step, "world_size": info.world_size, **host_info()})
        if class_weight is not None and start_step == 0:
            names = class_names(cfg)
            append_jsonl(log_path, {"step": 0, "class_weight": dict(zip(names, class_weight.tolist()))})
    ddp_model = DistributedDataParallel(model) if info.world_size > 1 else model

    loader = DataLoader(
        TrainBatches(scans, cfg, info.rank, info.world_size, unlabeled),
        batch_size=None,
        sampler=range(start_step, cfg.optim.steps),
        num_workers=cfg.num_workers,
        pin_memory=device.type == "cuda",
        generator=torch.Generator().manual_seed(cfg.seed),  # the global RNG is left alone
    )
    bar = progress_bar(total=cfg.optim.steps, initial=start_step, desc="seg-train", enabled=(progress and info.is_main))
    t0 = time.perf_counter()
    sums: dict[str, torch.Tensor] = {}
    count, done, lr = 0, start_step, learning_rate(start_step, cfg.optim)
    model.train()

    # ---- loop: after the body of step s, done = s + 1 steps are finished
    for batch in loader:
        step = int(batch["step"])
        used = elapsed_before + time.perf_counter() - t0
        time_fraction = budget_fraction(used, cfg.max_minutes) if cfg.optim.anneal_to == "budget" else 0.0
        lr = learning_rate(step, cfg.optim, time_fraction)
        for group in optimizer.param_groups:
            group["lr"] = lr
        torch.manual_seed(derived_seed(cfg.seed, _STEP, step, info.rank))  # dropout of this step only

        if cfg.mode == "supervised" or (cfg.mode == "semi" and in_burn_in(cfg.semi, step)):
            losses = supervised_step(ddp_model, batch, cfg, device, class_weight)
        elif cfg.mode == "semi":
            losses = semi_step(ddp_model, teacher, batch, cfg, device, class_weight)
        else:
            raise ValueError(f"mode must be 'supervised' or 'semi'; got {cfg.mode!r}")
        check_finite_loss(losses["loss"], step + 1)
        optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        grad_norm = (
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.optim.grad_clip) if cfg.optim.grad_clip > 0 else None
        )
        checked = grad_norm  # NaN weights would follow a non-finite gradient: stop before the step
        if checked is None:  # no clipping: the norm is taken for this check only (not logged)
            checked = torch.nn.utils.get_total_norm([p.grad for p in model.parameters() if p.grad is not None])
        check_finite_loss(losses["loss"], step + 1, checked)
        optimizer.step()
        if teacher is not None:
            update_teacher(teacher, model, cfg.semi, step)
        done = step + 1

        for key, value in losses.items():
            sums[key] = sums.get(key, 0.0) + value.detach().float()
        if grad_norm is not None:
            sums["grad_norm"] = sums.get("grad_norm", 0.0) + grad_norm.detach().float()
        count += 1
        bar.update(1)
        bar.set_postfix(loss=f"{losses['loss'].item():.3f}", lr=f"{lr:.2e}")
        elapsed = elapsed_before + time.perf_counter() - t0
        out_of_time = budget_used(elapsed, cfg.max_minutes)
        last = done == cfg.optim.steps or out_of_time

        if done % cfg.log_every == 0 or last:
            record = {"step": done, "lr": lr, "time": round(elapsed, 3)}
            for key, value in sums.items():
                record[key] = float(all_reduce_mean(torch.as_tensor(value / count, device=device)))
            sums, count = {}, 0
            if info.is_main:
                append_jsonl(log_path, record)

        if done % cfg.eval_every == 0 or last:
            sync_buffers(evaluated)
            summary, bins = evaluate_val(evaluated, cfg, val_scans, info)
            if teacher is not None:
                teacher_mode(teacher, cfg.semi.bn_mode)  # evaluation left it in train mode
            if summary is not None:
                last_summary = summary
                if info.is_main:
                    append_jsonl(log_path, {
                        "step": done,
                        "time": round(elapsed, 3),
                        "val_miou": summary["miou"],
                        "val_ece_per_scan": summary["ece_per_scan"],
                        "val_ece_pooled": summary["ece_pooled"],
                        "val_iou": summary["iou"],
                    })  # fmt: skip
                    plot_reliability(bins, out_dir / "reliability.png", title=f"step {done}")
                    bar.write(
                        f"step {done}: val mIoU {_pct(summary['miou'])}, ECE per scan "
                        f"{_pct(summary['ece_per_scan'])}, pooled {_pct(summary['ece_pooled'])}"
                    )
            if info.is_main:
                plot_learning_curve(read_jsonl(log_path), out_dir / "learning_curve.png", "step", CURVE_KEYS)

        periodic = done % cfg.checkpoint_every == 0 or last
        burn_in_end = 0 < cfg.semi.burn_in_steps == done  # also in mode "supervised": the same first steps
        if periodic or burn_in_end:
            if info.is_main:
                state = {
                    "format": CHECKPOINT_FORMAT,
                    "config": config_to_dict(cfg),
                    "step": done,
                    "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "scheduler": {"name": "warmup_cosine", "step": done, "lr": lr},
                    "ema": None if teacher is None else teacher.state_dict(),  # the mean teacher (mode "semi")
                    "rng": {"torch": torch.get_rng_state(), "seed": cfg.seed},
                    "elapsed": elapsed,
                    "metrics": last_summary,
                    "class_names": class_names(cfg),
                    "class_weight": class_weight,
                }
                if periodic:
                    save_checkpoint(out_dir / "checkpoints" / f"step_{done:07d}.pt", state, cfg.keep_checkpoints)
                if burn_in_end:  # kept whatever the rotation: `u4d experiment` starts the other arms from it
                    atomic_torch_save(out_dir / "burn_in.pt", state)
            barrier()
        if out_of_time:
            if info.is_main:
                bar.write(f"stopping at step {done}: wall-clock budget of {cfg.max_minutes} min used")
            break
    bar.close()

    # ---- final outputs: weights + config for seg-eval / seg-predict, and the last evaluation
    if info.is_main:
        atomic_torch_save(out_dir / "model.pt", {
            "format": CHECKPOINT_FORMAT,
            "config": config_to_dict(cfg),
            "step": done,
            "model": evaluated.state_dict(),  # the teacher in mode "semi"
            "metrics": last_summary,
            "class_names": class_names(cfg),
        })  # fmt: skip
        atomic_write_json(out_dir / "metrics.json", {"step": done, **(last_summary or {})})
    barrier()
    return last_summary or {}


def _pct(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.2f}%"


def _warn_config_changes(old: dict, new: dict, path: Path) -> None:
    """Resuming with another config is allowed (e.g. more steps) but not exact: warn which keys differ (a key the
    checkpoint predates, at its default value, is no change; nor is a since-removed key at its "off" value)."""
    old, acted = without_removed_keys(SegTrainConfig, old)
    defaults = {key: value for key, _, value in _differences({}, config_to_dict(SegTrainConfig()))}
    changed = [
        f"{key}: {a!r} -> {b!r}"
        for key, a, b in _differences(old, new)
        if key != "out_dir" and not (a is _ABSENT and defaults.get(key, _ABSENT) == b)
    ]
    changed += [f"{key}: {value!r} -> (removed)" for key, value in acted.items()]
    if changed:
        warnings.warn(f"{path}: resuming with a changed config ({'; '.join(changed)})", stacklevel=2)


class _Absent:
    def __repr__(self) -> str:
        return "(absent)"


_ABSENT = _Absent()  # a key one config has and the other lacks


def _differences(old: dict, new: dict, prefix: str = "") -> list[tuple[str, object, object]]:
    """(dotted key, old value, new value) of every leaf that differs; _ABSENT where a side lacks the key."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, _ABSENT), new.get(key, _ABSENT)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif isinstance(b, dict) and a is _ABSENT:
            out += _differences({}, b, f"{prefix}{key}.")
        elif a != b:
            out.append((f"{prefix}{key}", a, b))
    return out


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


def main(argv: list[str] | None = None) -> int:
    """`python -m segmentation.train CONFIG ...`: the same as `u4d seg-train`, handy under torchrun."""
    parser = argparse.ArgumentParser(prog="python -m segmentation.train", description=run_seg_train.__doc__)
    add_seg_train_arguments(parser)
    argv = sys.argv[1:] if argv is None else argv
    return exit_code_of(lambda args: run_seg_train(parse_command_line(parser, args)), argv)


if __name__ == "__main__":
    sys.exit(main())
