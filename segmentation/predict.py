"""Checkpoint + scans -> per-point class probabilities, the contract with `u4d_aug.uncertainty`.

`u4d seg-predict CKPT DATA --out DIR` writes, for every scan `DATA/sequences/XX/velodyne/NNNNNN.bin`,
`DIR/sequences/XX/probs/NNNNNN.npy`: float16 (N, K) softmax probabilities, rows in the order of the scan's
points (NaN/inf points are dropped with a counted warning, as `load_kitti_frame` drops them for every reader of
these files); a nuScenes root (the checkpoint's data.format, or --format) gives `DIR/sequences/SCENE/probs/TOKEN.npy`
per keyframe, rows those `NuscenesScanDataset` reads (ego returns within 1 m dropped); plus `DIR/manifest.json`
naming the checkpoint (sha256[:16]), its config and the test-time views (`--views N`: mean softmax over the scan's
mirror and turned views). Any segmentor that writes these files can drive U4D. Files are written atomically and
existing ones are skipped, so a re-run resumes; under torchrun each rank takes every world_size-th scan. Rank 0 holds
the run lock of DIR (`u4d_aug.runlock`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from torch import nn

from segmentation.mean_teacher import mean_view_probs, scan_views, view_count_error
from segmentation.models import SPVCNN, MinkUNet, SegModelConfig, build_model
from u4d_aug.config import config_from_dict
from u4d_aug.data.datasets import DATASET_FORMATS, SEMANTICKITTI_SPLITS, open_scans
from u4d_aug.data.formats import usable_rows
from u4d_aug.data.nuscenes import NUSCENES_VERSION
from u4d_aug.distributed import DistInfo, barrier, cleanup, init_distributed, shard
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_save_npy, atomic_write_json, file_sha256, remove_temp_files
from u4d_aug.io import load_checkpoint as load_torch_checkpoint
from u4d_aug.progress import progress_bar
from u4d_aug.run import checkpoint_kind
from u4d_aug.runlock import run_lock
from u4d_aug.validate import check_state_fits
from u4d_aug.weights import SEGMENTATION_KIND, exported_model, is_exported

MANIFEST_FORMAT = "u4d-seg-probs"


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint written by segmentation.train (also one older than the run layer's "kind"), or its exported
    float16 weights (`u4d_aug.weights`, then 'model' holds them cast back to float32 and 'step' the training step);
    on CPU, tensors and plain python only."""
    ckpt = load_torch_checkpoint(path, "segmentation checkpoint")
    if "model" not in ckpt or "config" not in ckpt:
        raise InputError(f"{path}: not a segmentation checkpoint (expected keys 'config' and 'model')")
    names = ckpt.get("class_names")
    if names is not None and not (isinstance(names, list) and all(isinstance(name, str) for name in names)):
        raise InputError(f"{path}: 'class_names' must be a list of class names, got {type(names).__name__}")
    if is_exported(ckpt):
        if ckpt.get("kind") != SEGMENTATION_KIND:
            raise InputError(f"{path}: exported {ckpt.get('kind')} weights, not a segmentation checkpoint")
        trained = ckpt.get("trained", {})
        if not isinstance(trained, dict):
            raise InputError(f"{path}: 'trained' must be a mapping (step, source), got {type(trained).__name__}")
        ckpt = {**ckpt, "model": exported_model(ckpt, str(path)), "step": trained.get("step")}
    elif checkpoint_kind(ckpt) != SEGMENTATION_KIND:
        kind = ckpt.get("kind") or ckpt.get("format")
        found = f"a {kind} checkpoint" if isinstance(kind, str) else "another kind of checkpoint"
        raise InputError(f"{path}: not a segmentation checkpoint ({found}; `u4d seg-train` writes model.pt)")
    return ckpt


def model_from_checkpoint(
    ckpt: dict, device: torch.device, source: str = "checkpoint", readout: str | None = None
) -> MinkUNet | SPVCNN:
    """Rebuild the net from the checkpoint's config['model'] and load its weights, in eval mode; `readout`
    (voxel | trilinear) replaces the config's way points read the voxel output (same weights)."""
    config = ckpt.get("config")
    if not isinstance(config, dict):
        raise InputError(f"{source}: no 'config' (the run's config, which says how to build the net)")
    fields = dict(config.get("model") or {})
    if readout is not None:
        fields["readout"] = readout
    model_cfg = config_from_dict(SegModelConfig, fields, source=f"{source} config")
    model = build_model(model_cfg)
    check_state_fits(ckpt.get("model"), model.state_dict(), source, "the checkpoint's weights must fit its config")
    try:
        model.load_state_dict(ckpt["model"])
    except (RuntimeError, TypeError, AttributeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{source}: its weights do not fit the net its config describes ({first})") from None
    return model.to(device).eval()


def checkpoint_data(ckpt: dict, data_format: str | None = None, version: str | None = None) -> tuple[str, str]:
    """(format, nuScenes version) of the scans to read: the given ones, else those the checkpoint trained on
    (data.format / data.nuscenes_version of its config; SemanticKITTI for checkpoints older than these keys)."""
    data = ckpt["config"].get("data") or {}
    data_format = data_format or data.get("format", "semantickitti")
    if data_format not in DATASET_FORMATS:
        raise InputError(f"data format {data_format!r}: expected one of {', '.join(DATASET_FORMATS)}")
    return data_format, version or data.get("nuscenes_version", NUSCENES_VERSION)


def class_names_of(ckpt: dict, dataset, num_classes: int) -> list[str]:
    """The checkpoint's class names, else the first num_classes of the dataset's label set."""
    return list(ckpt.get("class_names") or dataset.label_set.classes[:num_classes])


def checkpoint_hash(path: str | Path) -> str:
    """sha256 of the checkpoint file, first 16 hex digits (names the segmentor in manifests)."""
    return file_sha256(path)


@torch.no_grad()
def predict_probs(
    model: nn.Module, points: np.ndarray | torch.Tensor, device: torch.device, views: int = 1
) -> torch.Tensor:
    """Softmax probabilities (N, K) float32 on the CPU of one scan (N, 4); the model must be in eval mode.

    views > 1: test-time augmentation, the mean softmax over the scan's mirror and turned views
    (`mean_teacher.scan_views`), flips and turns the training augmentation draws; one view per forward.
    """
    points = torch.as_tensor(points, dtype=torch.float32).to(device)
    return mean_view_probs([model([view]) for view in scan_views(points, views)]).cpu()  # (N, K)


def scan_probs(
    model: nn.Module, points: np.ndarray, device: torch.device, num_classes: int, views: int = 1
) -> np.ndarray:
    """(N, K) float16 for all N rows of a raw scan; rows with NaN/inf coordinates or beyond 10 km
    (`formats.usable_rows`) get the uniform 1/K."""
    finite = usable_rows(points)
    probs = np.full((len(points), num_classes), 1.0 / num_classes, dtype=np.float32)
    if finite.any():
        probs[finite] = predict_probs(model, points[finite], device, views).numpy()
    return probs.astype(np.float16)


def probs_path(out_dir: str | Path, seq: str, frame: str) -> Path:
    """DIR/sequences/seq/probs/frame.npy."""
    return Path(out_dir) / "sequences" / seq / "probs" / f"{frame}.npy"


def predict_root(
    checkpoint: str | Path,
    data_root: str | Path,
    out_dir: str | Path,
    sequences: str | list[str] | None = None,
    dist_info: DistInfo | None = None,
    progress: bool = True,
    views: int = 1,
    readout: str | None = None,
    data_format: str | None = None,
    version: str | None = None,
) -> dict:
    """Write the probabilities of every scan of `sequences` under out_dir (skip existing) and the manifest.

    views > 1 average the softmax over mirror and turned views (predict_probs); the manifest records the count
    and the readout (`readout` replaces the checkpoint's, model_from_checkpoint). data_format / version: how to read
    data_root (None: as the checkpoint was trained, `checkpoint_data`).
    """
    info = dist_info or init_distributed("auto")
    with run_lock(out_dir, enabled=info.is_main):
        return predict_locked(
            checkpoint, data_root, Path(out_dir), sequences, info, progress, views, readout, data_format, version
        )


def predict_locked(
    checkpoint: str | Path,
    data_root: str | Path,
    out_dir: Path,
    sequences: str | list[str] | None,
    info: DistInfo,
    progress: bool,
    views: int,
    readout: str | None,
    data_format: str | None = None,
    version: str | None = None,
) -> dict:
    """The work of `predict_root` once the output folder is locked."""
    check_views(views)
    ckpt = load_checkpoint(checkpoint)
    model = model_from_checkpoint(ckpt, info.device, str(checkpoint), readout)
    num_classes = int(ckpt["config"].get("model", {}).get("num_classes", SegModelConfig.num_classes))
    data_format, version = checkpoint_data(ckpt, data_format, version)
    dataset = open_scans(data_root, sequences, False, data_format, version)
    sequences, entries = dataset.sequences, dataset.entries
    manifest = {
        "format": MANIFEST_FORMAT,
        "version": 1,
        "checkpoint": str(Path(checkpoint).resolve()),
        "checkpoint_sha256": checkpoint_hash(checkpoint),
        "config": ckpt["config"],
        "step": ckpt.get("step"),
        "num_classes": num_classes,
        "views": views,
        "readout": model.cfg.readout,
        "class_names": class_names_of(ckpt, dataset, num_classes),
        "dtype": "float16",
        "layout": "sequences/XX/probs/NNNNNN.npy, (N, K) rows in scan point order",
        "data_root": str(Path(data_root).resolve()),
        **({"data_format": data_format, "nuscenes_version": version} if data_format != "semantickitti" else {}),
        "sequences": sequences,
        "num_scans": len(entries),
        "complete": False,
    }
    manifest_path = out_dir / "manifest.json"
    _check_manifest(manifest_path, manifest)
    if info.is_main:
        remove_temp_files(out_dir)  # of killed writes; the other ranks start writing after the barrier
        atomic_write_json(manifest_path, manifest)
    barrier()

    mine = shard(entries, info.rank, info.world_size)
    written = skipped = 0
    for seq, frame in progress_bar(mine, desc="seg-predict", enabled=(progress and info.is_main), unit="scan"):
        target = probs_path(out_dir, seq, frame)
        if target.is_file():
            skipped += 1
            continue
        points = dataset.load_points(seq, frame)  # NaN/inf points dropped (warning); nuScenes: ego returns too
        atomic_save_npy(target, scan_probs(model, points, info.device, num_classes, views))
        written += 1
    barrier()
    if info.is_main:
        manifest["complete"] = True
        atomic_write_json(manifest_path, manifest)
    return {"written": written, "skipped": skipped, "num_scans": len(entries), "out_dir": str(out_dir)}


def _check_manifest(path: Path, manifest: dict) -> None:
    """A resumed run must use the same checkpoint, else the folder would mix two segmentors."""
    if not path.is_file():
        return
    try:
        old = json.loads(path.read_text())
    except json.JSONDecodeError:
        raise InputError(f"{path}: not valid json; remove it or choose another --out") from None
    if old.get("checkpoint_sha256") != manifest["checkpoint_sha256"]:
        raise InputError(
            f"{path}: written by checkpoint {old.get('checkpoint_sha256')}, not "
            f"{manifest['checkpoint_sha256']}; choose another --out (two segmentors' probabilities would mix)"
        )
    if old.get("views", 1) != manifest["views"]:
        raise InputError(
            f"{path}: written with --views {old.get('views', 1)}, not {manifest['views']}; "
            "choose another --out (probabilities of two test-time augmentations would mix)"
        )
    if old.get("readout", "voxel") != manifest["readout"]:
        raise InputError(
            f"{path}: written with readout {old.get('readout', 'voxel')}, not {manifest['readout']}; "
            "choose another --out (probabilities of two readouts would mix)"
        )


def check_views(views: int) -> None:
    """--views must name 1-4 mirror views or a multiple of 4 up to 32 (mirrors x turns, `scan_views`)."""
    error = view_count_error(views)
    if error is not None:
        raise InputError(f"--{error}")


def parse_sequences(values: list[str] | None) -> str | list[str] | None:
    """CLI --sequences: nothing -> all, one split name -> that split, else the listed sequences."""
    if not values:
        return None
    if len(values) == 1 and values[0] in SEMANTICKITTI_SPLITS:
        return values[0]
    return [v.strip() for value in values for v in value.split(",") if v.strip()]


def add_seg_predict_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d seg-predict CKPT DATA --out DIR [--sequences ..]`."""
    parser.add_argument("checkpoint", type=Path, help="segmentation checkpoint (.pt from u4d seg-train)")
    parser.add_argument(
        "data", type=Path, help="SemanticKITTI-layout root (ROOT/sequences/XX/velodyne) or nuScenes root"
    )
    parser.add_argument("--out", type=Path, required=True, help="output root: OUT/sequences/XX/probs/*.npy")
    parser.add_argument(
        "--sequences",
        nargs="+",
        default=None,
        help="sequences (e.g. 00 01), ranges (00-87) or a split name; default all",
    )
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    add_data_format_arguments(parser)
    add_views_argument(parser)
    add_readout_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_data_format_arguments(parser: argparse.ArgumentParser) -> None:
    """--format / --nuscenes-version: how DATA is laid out (default: as the checkpoint's training data was)."""
    parser.add_argument(
        "--format",
        choices=DATASET_FORMATS,
        default=None,
        help="layout of DATA: semantickitti or nuscenes (default: the checkpoint's data.format)",
    )
    parser.add_argument(
        "--nuscenes-version",
        default=None,
        help="nuScenes table folder under DATA, e.g. v1.0-mini (default: the checkpoint's data.nuscenes_version)",
    )


def add_readout_argument(parser: argparse.ArgumentParser) -> None:
    """--readout voxel|trilinear: how points read a MinkUNet's voxel output (default: the checkpoint's)."""
    parser.add_argument(
        "--readout",
        choices=["voxel", "trilinear"],
        default=None,
        help="MinkUNet: points read their voxel's logits (voxel) or the voxel softmax interpolated over the 8 "
        "nearest voxel centres (trilinear); default: as the checkpoint was trained",
    )


def add_views_argument(parser: argparse.ArgumentParser) -> None:
    """--views N: test-time augmentation over N mirror / turned views (1 = the scan only)."""
    parser.add_argument(
        "--views",
        type=int,
        default=1,
        help="test-time augmentation: mean softmax over the scan and its x/y/xy mirror views (1-4), or those four "
        "after each of N/4 turns about z by multiples of 90*4/N degrees (N a multiple of 4 up to 32); default 1",
    )


def run_seg_predict(args: argparse.Namespace) -> int:
    """`u4d seg-predict`: per-point probabilities of every scan (resumable, shardable with torchrun)."""
    info = init_distributed(args.device)
    try:
        result = predict_root(
            args.checkpoint,
            args.data,
            args.out,
            parse_sequences(args.sequences),
            dist_info=info,
            progress=not args.no_progress,
            views=args.views,
            readout=args.readout,
            data_format=args.format,
            version=args.nuscenes_version,
        )
    finally:
        cleanup()
    if info.is_main:
        where = " (rank 0's share)" if info.world_size > 1 else ""
        print(
            f"{result['num_scans']} scans: wrote {result['written']}, skipped {result['skipped']} existing"
            f"{where} -> {result['out_dir']}",
            file=sys.stderr,
        )
    return 0
