"""mIoU and ECE of a segmentation checkpoint on labeled scans (`u4d seg-eval CKPT DATA`).

One pass gives the confusion matrix (mmdet3d `seg_eval`) and the Calib3D ECE both per scan and pooled
(segmentation.metrics), as Calib3D's `[SegMetric, ECEMetric]` evaluator does on uncalibrated logits.
Under torchrun each rank evaluates every world_size-th scan and the counts are gathered. `evaluate_val` is the
periodic evaluation of a `u4d seg-train` run on its val scans, all ranks sharing one model.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from segmentation.config import SegTrainConfig, class_names
from segmentation.metrics import (
    CalibrationAccumulator,
    ConfusionMatrix,
    DistanceBands,
    iou_per_class,
    mean_iou,
    summarize,
    top_confusions,
)
from segmentation.plots import plot_confusion, plot_reliability
from segmentation.predict import (
    add_data_format_arguments,
    add_readout_argument,
    add_views_argument,
    check_views,
    checkpoint_data,
    class_names_of,
    load_checkpoint,
    model_from_checkpoint,
    parse_sequences,
    predict_probs,
)
from u4d_aug.data.datasets import NuscenesScanDataset, ScanDataset, open_scans
from u4d_aug.data.labels import SEMANTICKITTI_IGNORE
from u4d_aug.distributed import DistInfo, cleanup, init_distributed, shard
from u4d_aug.errors import InputError
from u4d_aug.io import check_output_file, dumps_json
from u4d_aug.progress import progress_bar


def accumulate(
    model: nn.Module,
    dataset: ScanDataset | NuscenesScanDataset,
    indices: Sequence[int],
    device: torch.device,
    num_classes: int,
    ignore_index: int = SEMANTICKITTI_IGNORE,
    rank: int = 0,
    world_size: int = 1,
    progress: bool = False,
    views: int = 1,
    bands: DistanceBands | None = None,
) -> tuple[ConfusionMatrix, CalibrationAccumulator]:
    """Confusion matrix + calibration over dataset[indices] (this rank's share, then gathered over ranks);
    views > 1 score the mean softmax over mirror / turned views (test-time augmentation, predict_probs);
    `bands`, when given, also gets each point by its distance band (filled in place, gathered too)."""
    was_training = model.training
    model.eval()
    cm = ConfusionMatrix(num_classes, ignore_index)
    calibration = CalibrationAccumulator(ignore_index)
    for index in progress_bar(shard(list(indices), rank, world_size), desc="eval", enabled=progress, leave=False):
        item = dataset[index]
        if item["labels"] is None:
            continue
        probs = predict_probs(model, item["points"], device, views)  # (N, K)
        target = torch.from_numpy(item["labels"])  # (N,) train ids, ignore id kept
        cm.update(probs.argmax(dim=1), target)
        calibration.update(probs, target)
        if bands is not None:
            bands.update(probs.argmax(dim=1), target, item["points"])
    model.train(was_training)
    if world_size > 1 and dist.is_available() and dist.is_initialized():
        gathered: list = [None] * world_size
        band_counts = [m.matrix for m in bands.matrices] if bands is not None else None
        dist.all_gather_object(gathered, (cm.matrix, calibration.scan_eces, calibration.pooled, band_counts))
        cm, calibration = ConfusionMatrix(num_classes, ignore_index), CalibrationAccumulator(ignore_index)
        if bands is not None:
            bands.matrices = [ConfusionMatrix(num_classes, ignore_index) for _ in bands.edges]
        for matrix, scan_eces, pooled, counts in gathered:
            cm.update_matrix(matrix)
            calibration.scan_eces.extend(scan_eces)
            calibration.pooled = calibration.pooled + pooled
            if bands is not None:
                bands.merge_matrices(counts)
    return cm, calibration


def summary_of(cm: ConfusionMatrix, calibration: CalibrationAccumulator, class_names: Sequence[str]) -> dict:
    """`metrics.summarize` plus the mIoU over the classes that have ground-truth points (sim-to-real)."""
    summary = summarize(cm, calibration, tuple(class_names))
    present = cm.matrix.sum(axis=1) > 0  # (K,) classes with ground-truth points
    iou = iou_per_class(cm.matrix)
    summary["classes_present"] = [name for name, p in zip(class_names, present) if p]
    summary["miou_present"] = float(np.nanmean(iou[present])) if present.any() else None
    summary["num_points"] = int(cm.matrix.sum())
    return summary


def evaluate(
    checkpoint: str | Path,
    data_root: str | Path,
    sequences: str | Sequence[str] | None = None,
    device: str = "auto",
    max_scans: int | None = None,
    reliability_png: str | Path | None = None,
    dist_info: DistInfo | None = None,
    progress: bool = False,
    views: int = 1,
    confusion_png: str | Path | None = None,
    readout: str | None = None,
    data_format: str | None = None,
    version: str | None = None,
) -> dict:
    """Summary dict (per-class IoU, mIoU, mIoU over present classes, ECE per scan and pooled, bins, confusion);
    views > 1: test-time augmentation over mirror / turned views (predict_probs); `readout` replaces the
    checkpoint's (model_from_checkpoint); data_format / version: how to read data_root (None: as the checkpoint
    was trained, `checkpoint_data`), which also gives the label set and its ignore id."""
    check_views(views)
    info = dist_info or init_distributed(device)
    ckpt = load_checkpoint(checkpoint)
    model = model_from_checkpoint(ckpt, info.device, str(checkpoint), readout)
    num_classes = model.cfg.num_classes
    data_format, version = checkpoint_data(ckpt, data_format, version)
    dataset = open_scans(data_root, sequences, True, data_format, version)
    labels = dataset.label_set
    if num_classes != labels.num_classes:
        raise InputError(
            f"{checkpoint}: a net of {num_classes} classes; the {data_format} scans of {data_root} carry "
            f"{labels.num_classes} train ids"
        )
    class_names = class_names_of(ckpt, dataset, num_classes)
    if len(dataset) == 0:
        what = "labels/*.label" if data_format == "semantickitti" else "lidarseg files"
        raise InputError(f"{data_root}: no labeled scan in sequences {dataset.sequences} ({what})")
    indices = evenly_spaced(len(dataset), max_scans)
    bands = DistanceBands(num_classes, labels.ignore_index)
    cm, calibration = accumulate(
        model, dataset, indices, info.device, num_classes, labels.ignore_index,
        info.rank, info.world_size, progress and info.is_main, views, bands,
    )  # fmt: skip
    summary = summary_of(cm, calibration, class_names)
    summary["bands"] = bands.summary(tuple(class_names))  # mIoU per range band from the sensor
    summary.update(
        checkpoint=str(checkpoint),
        step=ckpt.get("step"),
        data_root=str(data_root),
        sequences=dataset.sequences,
        views=views,
        readout=model.cfg.readout,
    )
    if reliability_png is not None and info.is_main:
        plot_reliability(calibration.pooled, reliability_png, title=Path(checkpoint).stem)
    if confusion_png is not None and info.is_main:
        name = f"{Path(checkpoint).parent.name}/{Path(checkpoint).name}"
        plot_confusion(cm.matrix, class_names, confusion_png, title=f"{name}: mIoU {100 * mean_iou(cm.matrix):.1f} %")
    return summary


def evenly_spaced(count: int, limit: int | None) -> list[int]:
    """All indices 0..count-1, or `limit` of them evenly spaced (first and last included)."""
    if limit is None or limit >= count:
        return list(range(count))
    return sorted({round(i) for i in np.linspace(0, count - 1, limit)})


def format_summary(summary: dict) -> str:
    """Human-readable table: per-class IoU (%) with the two classes each is most mistaken for, mIoU, mIoU over
    present classes, both ECEs (%)."""

    def pct(value: float | None) -> str:
        return "   n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{100 * value:6.2f}"

    present = set(summary.get("classes_present", []))
    names = list(summary["iou"])
    width = max(len(name) for name in names)
    confused = top_confusions(summary["confusion"]) if summary.get("confusion") is not None else None
    lines = [f"{'class':<{width}}  IoU (%)" + ("  its points predicted as (share)" if confused else "")]
    for k, (name, value) in enumerate(summary["iou"].items()):
        if name not in present:
            mark = "   (no ground truth)"
        elif confused is not None:
            mark = "  " + ", ".join(f"{names[c]} {100 * share:.0f} %" for c, share in confused[k])
        else:
            mark = ""
        lines.append(f"{name:<{width}}  {pct(value)}{mark}".rstrip())
    lines += [
        "",
        f"mIoU (classes with a union)         {pct(summary['miou'])} %",
        f"mIoU (classes with ground truth)    {pct(summary.get('miou_present'))} %",
        f"ECE per scan (Calib3D, mean)        {pct(summary['ece_per_scan'])} %",
        f"ECE pooled over all points          {pct(summary['ece_pooled'])} %",
        f"scans {summary['num_scans']}, points {summary.get('num_points', 'n/a')}",
    ]
    for band in summary.get("bands", []):
        low, high = band["range"]
        where = f"{low:g}-{high:g} m" if high is not None else f">= {low:g} m"
        lines.append(f"mIoU at {where:<12}                {pct(band['miou'])} %  ({band['points']} points)")
    return "\n".join(lines)


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


def add_seg_eval_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d seg-eval CKPT DATA [--sequences ..] [--json] [--png OUT] [--confusion-png OUT]`."""
    parser.add_argument("checkpoint", type=Path, help="segmentation checkpoint (.pt from u4d seg-train)")
    parser.add_argument("data", type=Path, help="SemanticKITTI-layout root with labels, or a nuScenes root (--format)")
    parser.add_argument(
        "--sequences", nargs="+", default=None, help="sequences (e.g. 08), ranges (88-99) or a split name; default all"
    )
    parser.add_argument("--json", action="store_true", help="print the summary as json")
    parser.add_argument("--png", type=Path, default=None, help="write the reliability diagram here")
    parser.add_argument(
        "--confusion-png", type=Path, default=None, help="write the row-normalised confusion matrix here"
    )
    parser.add_argument("--max-scans", type=int, default=None, help="evaluate this many evenly spaced scans")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    add_data_format_arguments(parser)
    add_views_argument(parser)
    add_readout_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_seg_eval(args: argparse.Namespace) -> int:
    """`u4d seg-eval`: print per-class IoU, mIoU and both ECEs; optionally the reliability diagram."""
    if args.max_scans is not None and args.max_scans < 1:
        raise InputError(f"--max-scans must be >= 1, got {args.max_scans}")
    check_output_file(args.png, "reliability diagram")
    check_output_file(args.confusion_png, "confusion matrix")
    info = init_distributed(args.device)
    try:
        summary = evaluate(
            args.checkpoint,
            args.data,
            parse_sequences(args.sequences),
            max_scans=args.max_scans,
            reliability_png=args.png,
            confusion_png=args.confusion_png,
            dist_info=info,
            progress=not (args.json or args.no_progress),
            views=args.views,
            readout=args.readout,
            data_format=args.format,
            version=args.nuscenes_version,
        )
    finally:
        cleanup()
    if info.is_main:
        print(dumps_json(summary, indent=2) if args.json else format_summary(summary))  # NaN as null
    return 0
