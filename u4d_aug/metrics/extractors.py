"""Feature extractors for FRD and FPD, trained here on the training split (upstream weights cannot be fetched).

FRD (Zyrianov et al. 2022; R2DM `metrics/extractor/rangenet.py`): a small RangeNet-style encoder-decoder
(downsampling along azimuth only, as RangeNet++ DarkNet) segmenting 5-channel range images
[range, x, y, z, remission] (range and xyz divided by the sensor's max range, remission in [0, 1], zeros where
there is no return). Features of one scan: the last decoder map (C, H, W), flattened, at 4096 fixed indices drawn
by `random.Random(0).sample(range(C*H*W), 4096)` (the LiDARGen/R2DM protocol) -> (4096,); pooled variant: the
spatial mean of that map -> (C,).

FPD (Shu et al. 2019; R2DM `metrics/extractor/pointnet.py`): a PointNet with a per-point segmentation head on
all H*W unprojected range-image points including the zero points of empty pixels (as R2DM), xyz divided by 80.
Feature = concat(global max-pooled feature (G), max over points of the head's fc1 (F1) and fc2 (F2)
activations) -> (G + F1 + F2,); 256 + 128 + 64 = 448-D with the defaults (R2DM's classifier: 1808-D).

Every checkpoint stores `hash` = sha256[:16] of (kind, model config, weights); FRD/FPD results record it and
`compare_results` refuses results made with different extractors. After training, the net's own segmentation
head is scored on held-out labelled scans (`heldout_scores`: pixel accuracy, mIoU over present classes) and the
figures are stored in the checkpoint and the log, so a reader can judge whether the features mean anything.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from u4d_aug.config import config_to_dict, load_config, save_config
from u4d_aug.data.beams import check_beams
from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, SEMANTICKITTI_IGNORE
from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.errors import InputError
from u4d_aug.io import append_jsonl, atomic_torch_save, load_checkpoint, read_jsonl, remove_temp_files
from u4d_aug.progress import progress_bar
from u4d_aug.range_view import encode_depth, project_batch, scatter_to_image, unproject
from u4d_aug.runlock import run_lock
from u4d_aug.validate import check_finite_config, check_finite_loss, check_positive
from u4d_aug.weights import exported_model, is_exported

logger = logging.getLogger(__name__)

ExtractorKind = Literal["frd", "fpd"]
EXTRACTOR_KINDS = ("frd", "fpd")
NUM_CLASSES = len(SEMANTICKITTI_CLASSES) + 1  # 19 train ids + ignore, which the loss skips
CALIBRATION_BATCHES = 16  # training batches that set the BatchNorm statistics after training
FRD_NUM_SAMPLES = 4096  # feature indices drawn with seed 0 (LiDARGen / R2DM)
FRD_SAMPLE_SEED = 0
FPD_POINT_SCALE = 80.0  # m, R2DM DATASET_MAX_DEPTH: PointNet input = xyz / 80


@dataclass
class ExtractorDataConfig:
    """Training scans and range-image geometry (R2DM: 64x1024, linear FOV rows)."""

    root: str = "data/toy"
    sequences: str | tuple[str, ...] = "train"  # split name or list of sequences
    val_sequences: str | tuple[str, ...] = "val"  # held-out scans scored after training (train.val_scans)
    sensor: str = "hdl64"
    height: int = 64
    width: int = 1024
    row_mode: Literal["beam", "linear"] = "linear"

    def __post_init__(self) -> None:
        check_positive(self, "height", "width", prefix="data.")


@dataclass
class ExtractorModelConfig:
    """Network widths: FRD base channels / levels; FPD global and head sizes."""

    base_channels: int = 32  # FRD encoder stage c, 2c, 4c, ...; decoder ends at base_channels
    levels: int = 3  # FRD azimuth downsamplings by 2
    global_dim: int = 256  # FPD G
    fc1_dim: int = 128  # FPD F1
    fc2_dim: int = 64  # FPD F2

    def __post_init__(self) -> None:
        check_positive(self, "base_channels", "levels", "global_dim", "fc1_dim", "fc2_dim", prefix="model.")


@dataclass
class ExtractorTrainConfig:
    """AdamW on random labelled scans, cross-entropy ignoring class 19."""

    steps: int = 2000
    batch_size: int = 4
    lr: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    log_every: int = 50
    checkpoint_every: int = 250  # steps between resumable snapshots (OUT/KIND_partial.pt); a re-run continues there
    val_scans: int = 40  # held-out scans (evenly spaced) scored after training; 0 = skip
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_finite_config(self, "train.")
        check_positive(self, "steps", "batch_size", "lr", "log_every", "checkpoint_every", prefix="train.")
        check_positive(self, "weight_decay", "val_scans", allow_zero=True, prefix="train.")


@dataclass
class ExtractorConfig:
    """`u4d train-extractor KIND CONFIG [key=value ...]`."""

    data: ExtractorDataConfig = field(default_factory=ExtractorDataConfig)
    model: ExtractorModelConfig = field(default_factory=ExtractorModelConfig)
    train: ExtractorTrainConfig = field(default_factory=ExtractorTrainConfig)
    out_dir: str = "runs/extractor"


# ------------------------------------------------------------------------------------------------------------
# networks


def _conv_block(c_in: int, c_out: int, stride: tuple[int, int] = (1, 1)) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.LeakyReLU(0.1),
        nn.Conv2d(c_out, c_out, 3, padding=1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.LeakyReLU(0.1),
    )


class RangeSegNet(nn.Module):
    """RangeNet-style range-view segmentation net: azimuth-only downsampling encoder, skip decoder, 1x1 head."""

    def __init__(self, in_channels: int = 5, base_channels: int = 32, levels: int = 3) -> None:
        super().__init__()
        widths = [base_channels * 2**i for i in range(levels + 1)]
        self.stem = _conv_block(in_channels, widths[0])
        self.down = nn.ModuleList(_conv_block(widths[i], widths[i + 1], stride=(1, 2)) for i in range(levels))
        self.up = nn.ModuleList(_conv_block(widths[i + 1] + widths[i], widths[i]) for i in reversed(range(levels)))
        self.head = nn.Conv2d(widths[0], NUM_CLASSES - 1, 1)
        self.feature_channels = widths[0]

    def decode(self, x: Tensor) -> Tensor:
        """(B, 5, H, W) -> last decoder map (B, C, H, W), the FRD feature map (before the head)."""
        skips = [self.stem(x)]
        for block in self.down:
            skips.append(block(skips[-1]))
        h = skips.pop()
        for block in self.up:
            skip = skips.pop()
            h = F.interpolate(h, size=skip.shape[-2:], mode="nearest")
            h = block(torch.cat([h, skip], dim=1))
        return h

    def logits(self, x: Tensor) -> Tensor:
        """(B, 5, H, W) -> (B, 19, H, W) class scores."""
        return self.head(self.decode(x))

    def forward(self, x: Tensor, labels: Tensor) -> Tensor:
        """Cross-entropy loss of (B, 5, H, W) images against (B, H, W) train ids (19 ignored)."""
        return F.cross_entropy(self.logits(x), labels, ignore_index=SEMANTICKITTI_IGNORE)


class PointNetSeg(nn.Module):
    """PointNet (Qi et al. 2017) with a per-point segmentation head; FPD features = [global, fc1, fc2] maxima."""

    def __init__(self, global_dim: int = 256, fc1_dim: int = 128, fc2_dim: int = 64) -> None:
        super().__init__()
        self.local = nn.Sequential(nn.Conv1d(3, 64, 1), nn.BatchNorm1d(64), nn.ReLU(), nn.Conv1d(64, 64, 1))
        self.global_mlp = nn.Sequential(
            nn.BatchNorm1d(64), nn.ReLU(), nn.Conv1d(64, 128, 1), nn.BatchNorm1d(128), nn.ReLU(),
            nn.Conv1d(128, global_dim, 1),
        )  # fmt: skip
        self.fc1 = nn.Sequential(nn.Conv1d(64 + global_dim, fc1_dim, 1), nn.BatchNorm1d(fc1_dim), nn.ReLU())
        self.fc2 = nn.Sequential(nn.Conv1d(fc1_dim, fc2_dim, 1), nn.BatchNorm1d(fc2_dim), nn.ReLU())
        self.head = nn.Conv1d(fc2_dim, NUM_CLASSES - 1, 1)
        self.feature_dim = global_dim + fc1_dim + fc2_dim

    def _layers(self, xyz: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(B, N, 3) -> global (B, G), fc1 (B, F1, N), fc2 (B, F2, N), logits (B, 19, N)."""
        local = self.local(xyz.transpose(1, 2))  # (B, 64, N)
        global_feature = self.global_mlp(local).amax(dim=2)  # (B, G)
        joined = torch.cat([local, global_feature[:, :, None].expand(-1, -1, local.shape[2])], dim=1)
        fc1 = self.fc1(joined)  # (B, F1, N)
        fc2 = self.fc2(fc1)  # (B, F2, N)
        return global_feature, fc1, fc2, self.head(fc2)

    def features(self, xyz: Tensor) -> Tensor:
        """(B, N, 3) points / 80 -> (B, G + F1 + F2) FPD features."""
        global_feature, fc1, fc2, _ = self._layers(xyz)
        return torch.cat([global_feature, fc1.amax(dim=2), fc2.amax(dim=2)], dim=1)

    def logits(self, xyz: Tensor) -> Tensor:
        """(B, N, 3) points / 80 -> (B, 19, N) class scores."""
        return self._layers(xyz)[3]

    def forward(self, xyz: Tensor, labels: Tensor) -> Tensor:
        """Cross-entropy loss of (B, N, 3) points against (B, N) train ids (19 ignored)."""
        return F.cross_entropy(self.logits(xyz), labels, ignore_index=SEMANTICKITTI_IGNORE)


def build_model(kind: str, model_cfg: ExtractorModelConfig) -> nn.Module:
    """Explicit factory: 'frd' -> RangeSegNet, 'fpd' -> PointNetSeg."""
    if kind == "frd":
        return RangeSegNet(5, model_cfg.base_channels, model_cfg.levels)
    elif kind == "fpd":
        return PointNetSeg(model_cfg.global_dim, model_cfg.fc1_dim, model_cfg.fc2_dim)
    raise InputError(f"extractor kind {kind!r} is not one of {', '.join(EXTRACTOR_KINDS)}")


# ------------------------------------------------------------------------------------------------------------
# inputs


def range_inputs(
    scans: list[np.ndarray], sensor: Sensor, height: int, width: int, row_mode: str, labels: list | None = None
) -> tuple[Tensor, Tensor | None, Tensor]:
    """Scans -> (B, 5, H, W) [range, x, y, z, remission] / max range, (B, H, W) train ids (19 empty), (B, H, W) mask."""
    proj = project_batch(
        [np.ascontiguousarray(s[:, :4], dtype=np.float32) for s in scans], sensor, height, width, row_mode
    )
    points = torch.cat([torch.as_tensor(s[:, :4], dtype=torch.float32) for s in scans])  # (N, 4)
    xyz = scatter_to_image(points[:, :3], proj, fill=0.0)  # (B, H, W, 3)
    depth = proj.depth  # (B, H, W) m, 0 where empty
    image = torch.cat(
        [depth[:, None] / sensor.max_range, xyz.permute(0, 3, 1, 2) / sensor.max_range, proj.reflectance[:, None]],
        dim=1,
    )  # (B, 5, H, W)
    image = image * proj.mask[:, None]
    target = None
    if labels is not None:
        flat = torch.cat([torch.as_tensor(np.asarray(lab), dtype=torch.int64) for lab in labels])
        target = scatter_to_image(flat, proj, fill=SEMANTICKITTI_IGNORE)  # (B, H, W)
    return image.float(), target, proj.mask


def point_inputs(image5: Tensor, mask: Tensor, sensor: Sensor, row_mode: str) -> Tensor:
    """(B, 5, H, W) range inputs -> (B, H*W, 3) unprojected points / 80, zeros at empty pixels (R2DM FPD)."""
    depth = image5[:, 0] * sensor.max_range  # (B, H, W) m
    encoded = torch.stack([encode_depth(depth, sensor.max_range), torch.zeros_like(depth)], dim=1)  # (B, 2, H, W)
    points, _ = unproject(encoded, sensor, row_mode, mask=mask)  # (B, H, W, 4), zeros where invalid
    return points[..., :3].reshape(points.shape[0], -1, 3) / FPD_POINT_SCALE


# ------------------------------------------------------------------------------------------------------------
# hashing, saving, loading


def _geometry(cfg: ExtractorConfig) -> dict[str, Any]:
    """Input geometry that changes the features as much as the weights do."""
    data = cfg.data
    return {"sensor": data.sensor, "height": data.height, "width": data.width, "row_mode": data.row_mode}


def weights_hash(kind: str, cfg: ExtractorConfig, state_dict: dict[str, Tensor]) -> str:
    """sha256[:16] of kind, model config, input geometry (sorted json) and every tensor's name, dtype, shape, bytes."""
    digest = hashlib.sha256()
    header = {"kind": kind, "model": config_to_dict(cfg.model), "input": _geometry(cfg)}
    digest.update(json.dumps(header, sort_keys=True).encode())
    for name in sorted(state_dict):
        tensor = state_dict[name].detach().cpu().contiguous()
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}".encode())
        digest.update(tensor.numpy().tobytes() if tensor.dtype != torch.bfloat16 else tensor.float().numpy().tobytes())
    return digest.hexdigest()[:16]


def save_extractor(
    path: str | Path, kind: str, model: nn.Module, cfg: ExtractorConfig, extra: dict | None = None
) -> str:
    """Write the checkpoint (kind, resolved config, weights, hash) atomically; returns the hash."""
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    digest = weights_hash(kind, cfg, state)
    atomic_torch_save(
        path, {"kind": kind, "config": config_to_dict(cfg), "state_dict": state, "hash": digest, **(extra or {})}
    )
    return digest


@dataclass
class Extractor:
    """A loaded, frozen feature net with its geometry and hash."""

    kind: str
    model: nn.Module
    hash: str
    sensor: Sensor
    height: int
    width: int
    row_mode: str
    path: str

    @property
    def feature_dims(self) -> dict[str, int]:
        """Feature names -> sizes: FRD {'frd': 4096, 'frd_pooled': C}; FPD {'fpd': G + F1 + F2}."""
        if self.kind == "frd":
            return {"frd": FRD_NUM_SAMPLES, "frd_pooled": self.model.feature_channels}
        return {"fpd": self.model.feature_dim}


def load_extractor(path: str | Path, device: str = "cpu") -> Extractor:
    """Load a checkpoint written by `save_extractor` (its stored hash must match the weights) or its exported
    float16 weights (`u4d_aug.weights`: checked against their weights_hash, named by the checkpoint's hash)."""
    path = Path(path)
    ckpt = load_checkpoint(path, "extractor checkpoint")
    exported = is_exported(ckpt)
    if ckpt.get("kind") not in EXTRACTOR_KINDS or not (exported or "state_dict" in ckpt):
        raise InputError(f"{path}: not an extractor checkpoint (expected keys kind, config, state_dict, hash)")
    cfg = load_config_dict(ckpt["config"], str(path))
    if exported:
        state_dict, digest = exported_model(ckpt, str(path)), ckpt.get("hash")
        if not isinstance(digest, str):
            raise InputError(f"{path}: exported extractor weights without the hash of their checkpoint")
    else:
        state_dict, digest = ckpt["state_dict"], weights_hash(ckpt["kind"], cfg, ckpt["state_dict"])
        if digest != ckpt.get("hash"):
            raise InputError(f"{path}: stored hash {ckpt.get('hash')} does not match the weights ({digest})")
    model = build_model(ckpt["kind"], cfg.model)
    model.load_state_dict(state_dict)
    model.eval().to(device)
    sensor = get_sensor(cfg.data.sensor)
    return Extractor(ckpt["kind"], model, digest, sensor, cfg.data.height, cfg.data.width, cfg.data.row_mode, str(path))


def load_config_dict(data: dict, source: str) -> ExtractorConfig:
    """Rebuild the resolved ExtractorConfig stored in a checkpoint."""
    from u4d_aug.config import config_from_dict

    return config_from_dict(ExtractorConfig, data, source=source)


def frd_sample_indices(num_values: int, num_samples: int = FRD_NUM_SAMPLES, seed: int = FRD_SAMPLE_SEED) -> np.ndarray:
    """Fixed feature indices: `random.seed(0); random.sample(range(C*H*W), 4096)` (LiDARGen/R2DM), own RNG."""
    if num_values < num_samples:
        raise InputError(f"FRD feature map has {num_values} values, fewer than the {num_samples} sampled ones")
    return np.asarray(random.Random(seed).sample(range(num_values), num_samples), dtype=np.int64)


@torch.no_grad()
def extract_features(extractor: Extractor, scans: list[np.ndarray], batch_size: int = 8) -> dict[str, np.ndarray]:
    """Scans (N_i, >=4) -> {'frd': (S, 4096), 'frd_pooled': (S, C)} or {'fpd': (S, G + F1 + F2)}, float64."""
    if not scans:
        raise InputError("extract_features: no scans given")
    device = next(extractor.model.parameters()).device
    out: dict[str, list[np.ndarray]] = {name: [] for name in extractor.feature_dims}
    indices = None
    for start in range(0, len(scans), batch_size):
        batch = scans[start : start + batch_size]
        image, _, mask = range_inputs(batch, extractor.sensor, extractor.height, extractor.width, extractor.row_mode)
        if extractor.kind == "frd":
            fmap = extractor.model.decode(image.to(device)).cpu()  # (B, C, H, W)
            flat = fmap.flatten(1)  # (B, C*H*W)
            if indices is None:
                indices = torch.from_numpy(frd_sample_indices(flat.shape[1]))
            out["frd"].append(flat[:, indices].double().numpy())
            out["frd_pooled"].append(fmap.mean(dim=(2, 3)).double().numpy())
        else:
            xyz = point_inputs(image, mask, extractor.sensor, extractor.row_mode)  # (B, H*W, 3)
            out["fpd"].append(extractor.model.features(xyz.to(device)).cpu().double().numpy())
    return {name: np.concatenate(parts) for name, parts in out.items()}


def compare_results(a: dict, b: dict) -> dict[str, float]:
    """Differences b - a of the metrics two results share; refuses FRD/FPD made with different extractor hashes.

    A result maps metric name -> {"value": float, "extractor_hash": str (FRD/FPD only), ...}, or is an
    `evaluate` result whose "table1" holds that mapping.
    """
    metrics_a, metrics_b = a.get("table1", a), b.get("table1", b)
    diffs: dict[str, float] = {}
    for name in sorted(set(metrics_a) & set(metrics_b)):
        entry_a, entry_b = metrics_a[name], metrics_b[name]
        if not isinstance(entry_a, dict) or not isinstance(entry_b, dict):
            continue
        hash_a, hash_b = entry_a.get("extractor_hash"), entry_b.get("extractor_hash")
        if hash_a != hash_b:
            raise InputError(
                f"compare_results: {name} was computed with extractor {hash_a} in one result and {hash_b} in the "
                "other; re-run both with the same extractor checkpoint"
            )
        value_a, value_b = entry_a.get("value"), entry_b.get("value")
        if value_a is not None and value_b is not None:
            diffs[name] = float(value_b) - float(value_a)
    return diffs


# ------------------------------------------------------------------------------------------------------------
# held-out check


@torch.no_grad()
def heldout_scores(
    extractor: Extractor, scans: list[np.ndarray], labels: list[np.ndarray], batch_size: int = 4
) -> dict:
    """Segmentation quality of the extractor's own head on labelled scans: pixel accuracy, IoU per present class.

    Scored on range-image pixels (FRD) or unprojected pixel points (FPD) whose projected label is not ignore;
    mIoU averages the classes present in the labels. A feature net that cannot segment held-out scans gives
    FRD/FPD figures that mean little, so `train_extractor` records these next to the hash.
    """
    if not scans or len(scans) != len(labels):
        raise InputError(f"heldout_scores: need as many label arrays as scans, got {len(scans)} and {len(labels)}")
    num = NUM_CLASSES - 1
    confusion = torch.zeros(num * num, dtype=torch.int64)  # row = label, column = prediction
    device = next(extractor.model.parameters()).device
    for start in range(0, len(scans), batch_size):
        stop = start + batch_size
        image, target, mask = range_inputs(
            scans[start:stop], extractor.sensor, extractor.height, extractor.width, extractor.row_mode,
            labels=labels[start:stop],
        )  # fmt: skip
        if extractor.kind == "frd":
            pred = extractor.model.logits(image.to(device)).argmax(1).cpu()  # (B, H, W)
        else:
            xyz = point_inputs(image, mask, extractor.sensor, extractor.row_mode)
            pred = extractor.model.logits(xyz.to(device)).argmax(1).cpu().reshape(target.shape)  # (B, H, W)
        keep = target != SEMANTICKITTI_IGNORE
        confusion += torch.bincount(target[keep] * num + pred[keep], minlength=num * num)
    confusion = confusion.reshape(num, num).double()
    true_positive = confusion.diagonal()
    support = confusion.sum(1)
    union = support + confusion.sum(0) - true_positive
    present = support > 0
    iou = true_positive / union.clamp_min(1)
    return {
        "scans": len(scans),
        "pixels": int(support.sum()),
        "accuracy": float(true_positive.sum() / support.sum().clamp_min(1)),
        "miou_present": float(iou[present].mean()) if bool(present.any()) else float("nan"),
        "iou": {SEMANTICKITTI_CLASSES[c]: float(iou[c]) for c in range(num) if present[c]},
    }


def _heldout_scans(dataset: Any, count: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """`count` evenly spaced labelled scans of `dataset` (all when it has fewer)."""
    picks = np.unique(np.linspace(0, len(dataset) - 1, num=min(count, len(dataset))).round().astype(int))
    items = [dataset[int(i)] for i in picks]
    return [it["points"] for it in items], [it["labels"] for it in items]


def _heldout_dataset(cfg: ExtractorConfig) -> Any:
    """The labelled scans of data.val_sequences, or None when train.val_scans = 0; errors name the field."""
    from u4d_aug.data.datasets import ScanDataset

    if cfg.train.val_scans <= 0:
        return None
    names = cfg.data.val_sequences
    try:
        dataset = ScanDataset(cfg.data.root, names if isinstance(names, str) else list(names), labeled_only=True)
    except InputError as error:
        raise InputError(f"data.val_sequences={names}: {error} (or set train.val_scans=0)") from None
    if len(dataset) == 0:
        raise InputError(f"{cfg.data.root}: no labelled scans in data.val_sequences={names} (or set train.val_scans=0)")
    return dataset


# ------------------------------------------------------------------------------------------------------------
# training


def train_extractor(kind: str, cfg: ExtractorConfig, progress: bool = True) -> tuple[Path, str]:
    """Train the FRD or FPD net on labelled training scans; writes out_dir/{kind}.pt + log; returns (path, hash).

    Holds out_dir/.KIND.lock (`u4d_aug.runlock`) while it runs: the other kind may train into the same folder. A run
    that fails before its log leaves no out_dir it created behind (its KIND_config.yaml is removed with it).
    """
    if kind not in EXTRACTOR_KINDS:
        raise InputError(f"extractor kind {kind!r} is not one of {', '.join(EXTRACTOR_KINDS)}")
    with run_lock(cfg.out_dir, name=f".{kind}.lock", scaffolding=(f"{kind}_config.yaml",)):
        return train_extractor_locked(kind, cfg, progress)


def train_extractor_locked(kind: str, cfg: ExtractorConfig, progress: bool = True) -> tuple[Path, str]:
    """The run of `train_extractor` once its lock is held: data, net, loop, held-out scores, checkpoint."""
    from u4d_aug.data.datasets import ScanDataset

    sequences = cfg.data.sequences if isinstance(cfg.data.sequences, str) else list(cfg.data.sequences)
    dataset = ScanDataset(cfg.data.root, sequences, labeled_only=True)
    if len(dataset) == 0:
        raise InputError(f"{cfg.data.root}: no labelled scans in sequences {cfg.data.sequences}")
    val_dataset = _heldout_dataset(cfg)  # opened before training so that a wrong split fails at once
    sensor = get_sensor(cfg.data.sensor)
    check_beams(dataset[0]["points"], sensor, f"{cfg.data.root}: first training scan")  # a warning
    rng = np.random.default_rng(cfg.train.seed)
    with torch.random.fork_rng():
        torch.manual_seed(cfg.train.seed)  # initial weights from the config seed, global state restored after
        model = build_model(kind, cfg.model).to(cfg.train.device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.train.lr, weight_decay=cfg.train.weight_decay)
    out_dir = Path(cfg.out_dir)
    removed = remove_temp_files(out_dir, kind)  # only this kind's: the other may be training
    if removed:
        logger.info("%s: removed %d temp file(s) of a killed run", out_dir, removed)
    save_config(cfg, out_dir / f"{kind}_config.yaml")
    log_path = out_dir / f"{kind}_log.jsonl"
    partial_path = out_dir / f"{kind}_partial.pt"
    done, seconds = resume_partial(partial_path, kind, cfg, model, optimizer, rng, log_path)
    model.train()
    start = time.perf_counter() - seconds
    bar = progress_bar(
        range(done + 1, cfg.train.steps + 1),
        desc=f"train-extractor {kind}",
        initial=done,
        total=cfg.train.steps,
        enabled=progress,
    )
    for step in bar:
        picks = rng.choice(len(dataset), size=min(cfg.train.batch_size, len(dataset)), replace=False)
        inputs, target = _batch_inputs(kind, [dataset[int(i)] for i in picks], sensor, cfg)
        loss = model(inputs, target)
        check_finite_loss(loss, step)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        bar.set_postfix(loss=f"{float(loss.detach()):.3f}", refresh=False)
        if step % cfg.train.log_every == 0 or step == cfg.train.steps:
            record = {"step": step, "loss": float(loss.detach()), "seconds": time.perf_counter() - start}
            append_jsonl(log_path, record)
            bar.write(json.dumps(record))
        if step % cfg.train.checkpoint_every == 0 and step < cfg.train.steps:
            save_partial(partial_path, kind, cfg, model, optimizer, rng, step, time.perf_counter() - start)
    recalibrate_batchnorm(model, _calibration_batches(kind, dataset, sensor, cfg))
    model.eval()
    extra: dict[str, Any] = {"steps": cfg.train.steps}
    if val_dataset is not None:
        frozen = Extractor(kind, model, "", sensor, cfg.data.height, cfg.data.width, cfg.data.row_mode, "")
        scores = heldout_scores(frozen, *_heldout_scans(val_dataset, cfg.train.val_scans))
        extra["heldout"] = scores
        append_jsonl(log_path, {"step": cfg.train.steps, "heldout": scores})
        logger.info(
            f"held-out {scores['scans']} scans of {cfg.data.val_sequences}: pixel accuracy {scores['accuracy']:.3f}, "
            f"mIoU over present classes {scores['miou_present']:.3f}"
        )
    path = out_dir / f"{kind}.pt"
    digest = save_extractor(path, kind, model, cfg, extra=extra)
    partial_path.unlink(missing_ok=True)  # finished: the snapshot has served
    return path, digest


def _batch_inputs(kind: str, items: list[dict], sensor: Sensor, cfg: ExtractorConfig) -> tuple[Tensor, Tensor]:
    """Dataset items -> (net input, target) on cfg.train.device: range image (B, 5, H, W) and (B, H, W) train ids
    for FRD, pixel points (B, H*W, 3) and (B, H*W) train ids for FPD."""
    image, target, mask = range_inputs(
        [it["points"] for it in items], sensor, cfg.data.height, cfg.data.width, cfg.data.row_mode,
        labels=[it["labels"] for it in items],
    )  # fmt: skip
    if kind == "frd":
        return image.to(cfg.train.device), target.to(cfg.train.device)
    xyz = point_inputs(image, mask, sensor, cfg.data.row_mode)  # (B, H*W, 3)
    return xyz.to(cfg.train.device), target.flatten(1).to(cfg.train.device)


def _calibration_batches(kind: str, dataset: Any, sensor: Sensor, cfg: ExtractorConfig) -> list[Tensor]:
    """Up to CALIBRATION_BATCHES training batches, drawn by their own RNG (seed train.seed): a resume draws alike."""
    rng = np.random.default_rng(cfg.train.seed)
    size = min(cfg.train.batch_size, len(dataset))
    count = min(CALIBRATION_BATCHES, max(1, len(dataset) // size))
    return [
        _batch_inputs(kind, [dataset[int(i)] for i in rng.choice(len(dataset), size=size, replace=False)], sensor, cfg)[
            0
        ]
        for _ in range(count)
    ]


@torch.no_grad()
def recalibrate_batchnorm(model: nn.Module, batches: list[Tensor]) -> None:
    """BatchNorm running statistics recomputed as plain means over `batches` with the final weights ("precise BN",
    Wu & Johnson 2021): the EMA of training lags weights that moved, and a small-batch net then segments (and
    embeds) differently in eval mode than it trained."""
    norms = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    if not norms or not batches:
        return
    momenta, was_training = [m.momentum for m in norms], model.training
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average over the calibration batches
    model.train()
    for batch in batches:
        model.logits(batch)
    for m, momentum in zip(norms, momenta):
        m.momentum = momentum
    model.train(was_training)


def save_partial(
    path: Path,
    kind: str,
    cfg: ExtractorConfig,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    rng: np.random.Generator,
    step: int,
    seconds: float,
) -> None:
    """Atomic snapshot of an unfinished extractor run: weights, optimizer, scan-sampling and torch RNG, step."""
    atomic_torch_save(
        path,
        {
            "kind": f"{kind}-partial",
            "config": config_to_dict(cfg),
            "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
            "optimizer": optimizer.state_dict(),
            "rng": rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "step": step,
            "seconds": seconds,
        },
    )


def resume_partial(
    path: Path,
    kind: str,
    cfg: ExtractorConfig,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    rng: np.random.Generator,
    log_path: Path,
) -> tuple[int, float]:
    """(steps done, seconds spent) of the snapshot at `path`, loaded into model/optimizer/rng; (0, 0) without one.

    The snapshot must come from the same config (else a one-line error: another run's folder); the log keeps the
    records up to its step, so a resumed run's log reads as one run's.
    """
    if not path.is_file():
        log_path.unlink(missing_ok=True)  # a fresh run writes its log afresh
        return 0, 0.0
    state = load_checkpoint(path, "unfinished extractor run")
    if state.get("kind") != f"{kind}-partial" or state.get("config") != config_to_dict(cfg):
        raise InputError(
            f"{path}: an unfinished {kind} run with another config; use another out_dir or delete it to start over"
        )
    model.load_state_dict(state["state_dict"])
    optimizer.load_state_dict(state["optimizer"])
    rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    step = int(state["step"])
    kept = [r for r in read_jsonl(log_path) if r.get("step", 0) <= step] if log_path.is_file() else []
    log_path.unlink(missing_ok=True)
    for record in kept:
        append_jsonl(log_path, record)
    logger.info("%s: resuming the unfinished %s run at step %d", path.parent, kind, step)
    return step, float(state["seconds"])


def add_train_extractor_arguments(parser: argparse.ArgumentParser) -> None:
    """`u4d train-extractor {frd,fpd} CONFIG [key=value ...]`."""
    parser.add_argument("kind", choices=EXTRACTOR_KINDS, help="frd: range-view net; fpd: PointNet")
    parser.add_argument("config", type=Path, help="yaml config (configs/extractor/*.yaml)")
    parser.add_argument("overrides", nargs="*", help="key.sub=value overrides, e.g. train.steps=100")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_train_extractor(args: argparse.Namespace) -> int:
    """Train one extractor and print its checkpoint path and hash."""
    cfg = load_config(ExtractorConfig, args.config, args.overrides)
    path, digest = train_extractor(args.kind, cfg, progress=not args.no_progress)
    print(f"{args.kind} extractor: {path} hash {digest}")
    return 0


__all__ = [
    "Extractor",
    "ExtractorConfig",
    "PointNetSeg",
    "RangeSegNet",
    "add_train_extractor_arguments",
    "compare_results",
    "extract_features",
    "heldout_scores",
    "load_extractor",
    "run_train_extractor",
    "train_extractor",
]
