"""Typed config of a segmentation training run (`u4d seg-train CONFIG [key=value ...]`).

Defaults here, yaml presets in configs/seg/*.yaml, `a.b=value` overrides on the command line
(`u4d_aug.config.load_config`). The resolved config is saved as OUT/config.yaml and inside every checkpoint.
Settings that measured as no-ops or losses were removed; each class's `REMOVED_KEYS` names them with
the value that meant "off" and why, so that a config naming one is a one-line error and a saved config holding
one at its "off" value still reads (`u4d_aug.config.saved_config`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

from segmentation.data import AugmentConfig
from segmentation.mean_teacher import MeanTeacherConfig
from segmentation.models import SegModelConfig
from u4d_aug.data.datasets import DATASET_FORMATS
from u4d_aug.data.labels import LabelSet, label_set
from u4d_aug.data.nuscenes import NUSCENES_VERSION
from u4d_aug.validate import check_finite_config

Sequences = str | list[str | int] | None  # split name ('train' / 'val' / 'test'), a list of sequences, or all
_WARM_RESTART = (
    "a warm restart of the lr changed nothing (3 seeds, benchmarks/results/segmentation/experiment_cpu_tenpct_seq)"
)


@dataclass
class SegDataConfig:
    """Where the scans are and which of them train / validate; the format also sets the classes and ignore id."""

    root: Path = Path("data/sim")
    # layout of root, and with it the label set (u4d_aug.data.labels.label_set): "semantickitti" = sequences/XX/velodyne
    # (19 classes, ignore 19); "nuscenes" = the v1.0 tables under ROOT/<version>/ (16 lidarseg classes, ignore 16)
    format: Literal["semantickitti", "nuscenes"] = "semantickitti"
    nuscenes_version: str = NUSCENES_VERSION  # format nuscenes: the table folder ROOT/<version>/ (or v1.0-mini)
    sensor: str = "hdl64"  # u4d_aug.data.sensors.get_sensor name or yaml: LaserMix pitch range in mode "semi"
    # SemanticKITTI: a split name, a list like ["00", "01"], a range "00-87", or null = all; nuScenes: scene names,
    # numbers (61 = scene-0061) or ranges of them ("1-100"), or null = all scenes (no built-in split)
    train_sequences: Sequences = "train"
    val_sequences: Sequences = "val"
    # labeled part of the train scans (LaserMix splits, written under OUT/splits/)
    label_fraction: float = 1.0
    split_mode: Literal["uniform", "sequence"] = "uniform"
    split_seed: int = 0
    # mode "semi": the places the unlabeled real scans come from (the data-scarce setting: a pool of a few places,
    # none of them labelled); null = every train scan outside the labelled split
    unlabeled_sequences: Sequences = None
    # training part of each scan (CPU presets; evaluation keeps every point): a random azimuth sector of this many
    # degrees (None = the whole scan; keeps the point density), then at most max_points of it at random
    sector_deg: float | None = None
    max_points: int | None = None
    val_max_scans: int | None = None  # evenly spaced subset of the val scans for the periodic evaluation

    def __post_init__(self) -> None:
        check_finite_config(self, "data.")
        if self.format not in DATASET_FORMATS:
            raise ValueError(f"data.format must be one of {', '.join(DATASET_FORMATS)}; got {self.format!r}")
        # yaml reads 00 and 01 as integers: store sequence names as the folder names '00', '01'
        for name in ("train_sequences", "val_sequences", "unlabeled_sequences"):
            value = getattr(self, name)
            if isinstance(value, (list, tuple)):
                setattr(self, name, [f"{v:02d}" if isinstance(v, int) else str(v) for v in value])
        if not 0.0 < self.label_fraction <= 1.0:
            raise ValueError(f"data.label_fraction must be in (0, 1], got {self.label_fraction}")
        if self.sector_deg is not None and not 0.0 < self.sector_deg <= 360.0:
            raise ValueError(f"data.sector_deg must be in (0, 360] or null, got {self.sector_deg}")
        if self.max_points is not None and self.max_points < 1:
            raise ValueError(f"data.max_points must be >= 1 or null, got {self.max_points}")
        if self.val_max_scans is not None and self.val_max_scans < 1:
            raise ValueError(f"data.val_max_scans must be >= 1 or null, got {self.val_max_scans}")

    @property
    def label_set(self) -> LabelSet:
        """Class names, ignore id and raw -> train id map of the scans (from `format`)."""
        return label_set(self.format)


@dataclass
class SegOptimConfig:
    """AdamW with linear warm-up then cosine decay to min_lr_ratio * lr (per step), gradient clipping."""

    lr: float = 2e-3
    weight_decay: float = 0.01  # on weights with >= 2 dims only (biases and norms are not decayed)
    betas: tuple[float, float] = (0.9, 0.999)
    warmup_steps: int = 100
    min_lr_ratio: float = 0.01
    steps: int = 2000
    batch_size: int = 2  # scans per step over all ranks (each rank takes batch_size / world_size)
    grad_clip: float = 10.0  # max global grad norm; 0 = off
    # what the cosine decays over: "steps" = optim.steps; "budget" = whichever ends first of optim.steps and the
    # wall-clock budget max_minutes (progress = max(step share, time share)), so a slower or busier machine still
    # anneals to min_lr inside the budget instead of being cut at a high lr (budgeted training, Li et al. 2020)
    anneal_to: Literal["steps", "budget"] = "steps"

    REMOVED_KEYS: ClassVar[dict] = {"restart_step": (0, _WARM_RESTART), "restart_lr": (None, _WARM_RESTART)}

    def __post_init__(self) -> None:
        check_finite_config(self, "optim.")
        if self.weight_decay < 0 or self.grad_clip < 0:
            raise ValueError(
                f"optim.weight_decay and optim.grad_clip must be >= 0, got {self.weight_decay}, {self.grad_clip}"
            )
        if not all(0.0 <= beta < 1.0 for beta in self.betas):
            raise ValueError(f"optim.betas must be in [0, 1), got {list(self.betas)}")
        if self.anneal_to not in ("steps", "budget"):
            raise ValueError(f"optim.anneal_to must be 'steps' or 'budget'; got {self.anneal_to!r}")
        if self.steps < 1 or self.batch_size < 1 or self.warmup_steps < 0:
            raise ValueError("optim.steps and optim.batch_size must be >= 1 and optim.warmup_steps >= 0")
        if self.lr <= 0 or not 0.0 <= self.min_lr_ratio <= 1.0:
            raise ValueError("optim.lr must be positive and optim.min_lr_ratio in [0, 1]")


@dataclass
class LossConfig:
    """Supervised loss = ce_weight * CE + lovasz_weight * Lovász-softmax (Cylinder3D uses 1 + 3).

    class_weighting "inverse_sqrt" weights the CE of class c by f_c^(-1/2) (f_c = its share of the labelled
    training points, as SalsaNext), scaled so the mean weight per training point is 1 and capped at
    max_class_weight; "none" = plain CE (mmdet3d MinkUNet).
    """

    ce_weight: float = 1.0
    lovasz_weight: float = 0.0  # 0 = cross-entropy only, as mmdet3d MinkUNet
    label_smoothing: float = 0.0
    class_weighting: Literal["none", "inverse_sqrt"] = "none"
    max_class_weight: float = 50.0
    # "voxel": the training losses read one logit row per occupied voxel of the finest grid, labelled by the
    # majority of its points (torchsparse / SPVNAS style; MinkUNet only, whose points share their voxel's logits
    # anyway): 2-4x fewer rows for the CE and the Lovász sort. "point": every point (mmdet3d). Evaluation is per point.
    level: Literal["point", "voxel"] = "point"

    REMOVED_KEYS: ClassVar[dict] = {
        "point_fraction": (1.0, "point losses on a quarter of the points lost 7 mIoU points to voxel losses, "
                           "benchmarks/results/segmentation/seg_cpu_rich; use loss.level"),
    }  # fmt: skip

    def __post_init__(self) -> None:
        check_finite_config(self, "loss.")
        if min(self.ce_weight, self.lovasz_weight) < 0 or not 0.0 <= self.label_smoothing < 1.0:
            raise ValueError("loss.ce_weight and loss.lovasz_weight must be >= 0 and loss.label_smoothing in [0, 1)")
        if self.class_weighting not in ("none", "inverse_sqrt"):
            raise ValueError(f"loss.class_weighting must be 'none' or 'inverse_sqrt'; got {self.class_weighting!r}")
        if self.max_class_weight < 1.0:
            raise ValueError(f"loss.max_class_weight must be >= 1; got {self.max_class_weight}")
        if self.level not in ("point", "voxel"):
            raise ValueError(f"loss.level must be 'point' or 'voxel'; got {self.level!r}")


@dataclass
class BankConfig:
    """A bank of generated scans (SemanticKITTI layout, labels absent) mixed into the unlabeled stream."""

    path: Path = Path("banks/u4d")
    ratio: float = 0.5  # share of the unlabeled scans of a step drawn from this bank


@dataclass
class SemiConfig(MeanTeacherConfig):
    """Mode "semi": mean teacher + LaserMix hyper-parameters and the unlabeled stream's sources.

    Each unlabeled scan comes from bank i with probability banks[i].ratio, otherwise from the unlabeled
    part of the label split (ratio 1 - sum of the bank ratios; with label_fraction 1 that is the whole train set).
    """

    banks: list[BankConfig] = field(default_factory=list)
    # diagnostic upper bound: the unlabeled scans' own label files replace the teacher's pseudo-labels in L_mix
    # (every point, no threshold), so a run measures what the loop gives with perfect pseudo-labels; the scans
    # still count as unlabeled for L_mt and the split. Needs a label file for every unlabeled scan (no banks).
    oracle_labels: bool = False

    REMOVED_KEYS: ClassVar[dict] = {
        "teacher_views": (1, "pseudo-labels from mirror views changed nothing (+0.08 +- 0.35 points, 2 seeds) at 4 "
                          "teacher forwards a scan, benchmarks/results/segmentation/experiment_cpu_tenpct_seq"),
        "burn_in_teacher": ("copy", "the burn-in teacher is the student (Unbiased Teacher), which lets arms share "
                            "burn_in.pt; 'ema' was the setting of the early regimes where the mean teacher lost"),
    }  # fmt: skip

    def __post_init__(self) -> None:
        check_finite_config(self, "semi.")
        ratios = [bank.ratio for bank in self.banks]
        if any(r < 0 for r in ratios) or sum(ratios) > 1.0 + 1e-9:
            raise ValueError(f"semi.banks ratios must be >= 0 and sum to <= 1; got {ratios}")
        if not 0.0 <= self.ema_decay <= 1.0 or not 0.0 <= self.pseudo_threshold <= 1.0:
            raise ValueError("semi.ema_decay and semi.pseudo_threshold must be in [0, 1]")
        if self.consistency_rampup_steps < 0 or self.burn_in_steps < 0:
            raise ValueError(
                "semi.consistency_rampup_steps and semi.burn_in_steps must be >= 0, got "
                f"{self.consistency_rampup_steps} and {self.burn_in_steps}"
            )
        if self.pseudo_class_share is not None and not 0.0 < self.pseudo_class_share <= 1.0:
            raise ValueError(f"semi.pseudo_class_share must be in (0, 1] or null; got {self.pseudo_class_share}")
        if self.oracle_labels and self.banks:
            raise ValueError("semi.oracle_labels needs label files for every unlabeled scan; banks have none")


@dataclass
class SegTrainConfig:
    """One training run: data, net, optimiser, loss, augmentation and the loop's bookkeeping."""

    mode: Literal["supervised", "semi"] = "supervised"  # "semi": LaserMix mean teacher (segmentation/semi.py)
    data: SegDataConfig = field(default_factory=SegDataConfig)
    model: SegModelConfig = field(default_factory=SegModelConfig)
    optim: SegOptimConfig = field(default_factory=SegOptimConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    semi: SemiConfig = field(default_factory=SemiConfig)  # used in mode "semi" only
    eval_every: int = 500  # steps; the last step is always evaluated
    checkpoint_every: int = 500  # steps; the last step always writes one
    keep_checkpoints: int = 2  # newest OUT/checkpoints/step_*.pt kept; 0 = keep all
    log_every: int = 10  # steps between train records in OUT/log.jsonl
    max_minutes: float = 0.0  # wall-clock budget: stop (evaluate + checkpoint) once exceeded; 0 = off
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    num_workers: int = 0  # DataLoader workers that load + augment scans
    threads: int = 0  # torch intra-op threads per process; 0 = torch's default (OMP_NUM_THREADS)
    out_dir: Path = Path("runs/seg")

    def __post_init__(self) -> None:
        check_finite_config(self)
        for name in ("eval_every", "checkpoint_every", "log_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if min(self.keep_checkpoints, self.num_workers, self.threads, self.max_minutes) < 0:
            raise ValueError("keep_checkpoints, num_workers, threads and max_minutes must be >= 0")
        if self.optim.anneal_to == "budget" and self.max_minutes <= 0:
            raise ValueError("optim.anneal_to=budget needs a wall-clock budget: set max_minutes > 0")
        labels = self.data.label_set
        if self.augment.paste_classes is None:  # the default: the label set's thing classes
            self.augment.paste_classes = list(labels.things)
        unknown = [name for name in self.augment.paste_classes if name not in labels.classes]
        if unknown:
            raise ValueError(f"augment.paste_classes: unknown class names {unknown}; valid: {list(labels.classes)}")
        if self.loss.level == "voxel" and self.model.name != "minkunet":
            raise ValueError(
                f"loss.level=voxel needs model.name=minkunet (the {self.model.name} head reads points); use point"
            )


def class_names(cfg: SegTrainConfig) -> list[str]:
    """Train-id names of the net's classes (the data's label set)."""
    names = list(cfg.data.label_set.classes[: cfg.model.num_classes])
    return names + [f"class_{k}" for k in range(len(names), cfg.model.num_classes)]
