"""Semi-supervised LaserMix mean-teacher step and its unlabeled stream (LaserMix `SemiBase3DSegmentor.loss`).

One step takes B labeled scans (GT) and B unlabeled scans: the teacher (EMA of the student) pseudo-labels
the unlabeled scans (confidence < threshold -> ignore id), LaserMix mixes each (labeled, unlabeled) pair
into 2 scans, and the student's loss is L = w_sup L_sup + w_mix L_mix + w_mt MSE(softmax s, softmax t) on
the unlabeled scans. The unlabeled scans come from the unlabeled part of the label split and from banks of
generated scans (SemanticKITTI layout, labels absent), source drawn per slot with the configured ratios.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from segmentation.config import SegTrainConfig, SemiConfig
from segmentation.data import FrameId, augment, load_or_make_split, training_subset
from segmentation.lasermix import lasermix
from segmentation.losses import segmentation_loss, voxel_targets
from segmentation.mean_teacher import (
    consistency_loss,
    copy_buffers,
    ema_update,
    pseudo_labels,
    total_loss,
)
from u4d_aug.data.datasets import NuscenesScanDataset, ScanDataset, open_scans
from u4d_aug.data.sensors import get_sensor
from u4d_aug.errors import InputError
from u4d_aug.seeding import derived_seed

# seed domains of the semi-supervised streams (train.py uses 1..3)
_SOURCE, _UNLABELED, _MIX = 4, 5, 6


def _seed(*parts: int) -> int:

    return derived_seed(*parts)


class UnlabeledStream:
    """Unlabeled scans of step s, slot j: source drawn with the ratios, then a uniform scan of that source.

    Sources: [unlabeled part of the split (ratio 1 - sum of bank ratios), bank 0, bank 1, ...]; draws are
    seeded by (seed, step, slot) only, so they do not depend on ranks, workers or resumption.
    """

    def __init__(self, sources: list[ScanDataset | NuscenesScanDataset], ratios: list[float], names: list[str]) -> None:
        kept = [(s, r, n) for s, r, n in zip(sources, ratios, names) if r > 0]
        if not kept:
            raise InputError("semi: the unlabeled stream has no source with a positive ratio")
        for source, _, name in kept:
            if len(source) == 0:
                raise InputError(f"{name}: no scan in this unlabeled source (expected sequences/XX/velodyne/*.bin)")
        self.sources = [s for s, _, _ in kept]
        self.names = [n for _, _, n in kept]
        self.ratios = torch.tensor([r for _, r, _ in kept], dtype=torch.float64)

    def pick(self, seed: int, step: int, slot: int) -> tuple[int, int]:
        """(source index, scan index) of unlabeled slot `slot` of step `step`."""
        generator = torch.Generator().manual_seed(_seed(seed, _SOURCE, step, slot))
        source = int(torch.multinomial(self.ratios, 1, generator=generator))
        index = int(torch.randint(len(self.sources[source]), (1,), generator=generator))
        return source, index

    def load(self, seed: int, step: int, slot: int, with_labels: bool = False) -> dict:
        """The picked scan: dict(points (N, 4) float32 numpy, source name, seq, frame[, labels (N,) int64]).

        Labels are dropped unless with_labels (the oracle diagnostic), which then requires them.
        """
        source, index = self.pick(seed, step, slot)
        item = self.sources[source][index]
        out = {"points": item["points"], "source": self.names[source], "seq": item["seq"], "frame": item["frame"]}
        if with_labels:
            if item["labels"] is None:
                raise InputError(
                    f"{self.names[source]}: sequence {item['seq']} frame {item['frame']} has no label file; "
                    "semi.oracle_labels needs one for every unlabeled scan"
                )
            out["labels"] = item["labels"]
        return out


def unlabeled_stream(cfg: SegTrainConfig) -> UnlabeledStream:
    """Unlabeled split of the train sequences (split file written by train_scans) + the configured banks (banks are
    SemanticKITTI-layout folders whatever data.format is)."""
    data = cfg.data
    split = open_scans(data.root, data.train_sequences, False, data.format, data.nuscenes_version)
    if cfg.data.label_fraction < 1.0:
        labeled_frames = open_scans(data.root, data.train_sequences, True, data.format, data.nuscenes_version).entries
        _, unlabeled = load_or_make_split(
            Path(cfg.out_dir), labeled_frames, cfg.data.label_fraction, cfg.data.split_seed, cfg.data.split_mode
        )
        # the unlabeled part of the split, plus train scans that have no label file at all
        chosen, labeled_set = set(unlabeled), set(labeled_frames)
        split.entries = [entry for entry in split.entries if entry in chosen or entry not in labeled_set]
    if data.unlabeled_sequences is not None:
        split.entries = scarce_pool(split.entries, cfg)
    sources, ratios, names = [split], [1.0 - sum(b.ratio for b in cfg.semi.banks)], [f"{cfg.data.root} (split)"]
    for i, bank in enumerate(cfg.semi.banks):
        if not bank.path.is_dir():
            raise InputError(f"semi.banks[{i}].path: {bank.path} not found (expected a SemanticKITTI-layout root)")
        sources.append(ScanDataset(bank.path, None))
        ratios.append(bank.ratio)
        names.append(str(bank.path))
    return UnlabeledStream(sources, ratios, names)


def scarce_pool(entries: list[FrameId], cfg: SegTrainConfig) -> list[FrameId]:
    """The unlabeled scans of data.unlabeled_sequences only (the data-scarce setting); InputError when a named place
    is labelled or holds no unlabeled train scan."""
    data = cfg.data
    pool = open_scans(data.root, data.unlabeled_sequences, False, data.format, data.nuscenes_version)
    places = {seq for seq, _ in pool.entries}
    available = {seq for seq, _ in entries}
    if data.label_fraction < 1.0:
        labeled_frames = open_scans(data.root, data.train_sequences, True, data.format, data.nuscenes_version).entries
        labeled, _ = load_or_make_split(
            Path(cfg.out_dir), labeled_frames, data.label_fraction, data.split_seed, data.split_mode
        )
        overlap = sorted(places & {seq for seq, _ in labeled})
        if overlap:
            raise InputError(
                f"data.unlabeled_sequences: {', '.join(overlap)} hold labelled scans of the split; the unlabeled pool "
                "must come from places with no labelled scan (data.split_mode=sequence)"
            )
    missing = sorted(places - available)
    if missing:
        raise InputError(
            f"data.unlabeled_sequences: {', '.join(missing)} are not unlabeled train places "
            f"(data.train_sequences: {data.train_sequences})"
        )
    return [entry for entry in entries if entry[0] in places]


def load_unlabeled(
    stream: UnlabeledStream, cfg: SegTrainConfig, step: int, slots: range
) -> tuple[list[torch.Tensor], list[torch.Tensor] | None]:
    """Loaded, subsampled, augmented unlabeled scans (N_j, 4) of `step` for these slots of the global batch,
    and with semi.oracle_labels their own labels (N_j,) (else None)."""
    scans, labels = [], []
    for slot in slots:
        item = stream.load(cfg.seed, step, slot, with_labels=cfg.semi.oracle_labels)
        scan = torch.from_numpy(item["points"])  # (N, 4)
        generator = torch.Generator().manual_seed(_seed(cfg.seed, _UNLABELED, step, slot))
        keep = training_subset(scan, cfg.data.sector_deg, cfg.data.max_points, generator)
        scans.append(augment(scan[keep], generator, cfg.augment))
        if cfg.semi.oracle_labels:
            labels.append(torch.from_numpy(item["labels"])[keep])
    return scans, (labels if cfg.semi.oracle_labels else None)


def pitch_range(cfg: SegTrainConfig) -> tuple[float, float]:
    """LaserMix pitch range (down, up) in degrees: semi.pitch_range_deg, else the sensor's linear FOV."""
    if cfg.semi.pitch_range_deg is not None:
        down, up = cfg.semi.pitch_range_deg
        return (down, up)
    sensor = get_sensor(cfg.data.sensor)
    return (sensor.fov_down_deg, sensor.fov_up_deg)


def semi_step(
    student: nn.Module,
    teacher: nn.Module,
    batch: dict,
    cfg: SegTrainConfig,
    device: torch.device,
    class_weight: torch.Tensor | None = None,
) -> dict:
    """Losses of one labeled + unlabeled batch: {"loss", "loss_sup", "loss_mix", "loss_mt", "pseudo_kept"}.

    class_weight (K,) weights the CE of the supervised and the LaserMix-mixed losses (loss.class_weighting).
    With loss.level "voxel" the three losses read the occupied voxels of each scan (majority labels of the GT /
    pseudo-labelled points; L_mt between the student's and the teacher's voxels of the unlabeled scans).
    """
    labeled = [p.to(device) for p in batch["points"]]  # B x (N_b, 4)
    targets = [t.to(device) for t in batch["labels"]]  # B x (N_b,) train ids
    unlabeled = [p.to(device) for p in batch["unlabeled"]]  # B x (M_b, 4)
    if len(labeled) != len(unlabeled):
        raise ValueError(f"semi batch needs as many unlabeled as labeled scans; got {len(unlabeled)} vs {len(labeled)}")

    voxel = cfg.loss.level == "voxel"  # losses on voxel rows (majority labels) instead of points
    # teacher: pseudo-labels y_hat (sum M_b,) of the unlabeled scans, ignore id below the threshold
    with torch.no_grad():
        if voxel:
            teacher_out = teacher(unlabeled, voxel_output=True)
            teacher_logits = teacher_out.logits  # (V_u, K) voxels of the unlabeled scans
            teacher_point_logits = teacher_out.logits[teacher_out.inverse]  # (sum M_b, K)
        else:
            teacher_logits = teacher_point_logits = teacher(unlabeled)  # (sum M_b, K)
    ignore = cfg.data.label_set.ignore_index
    pseudo, _ = pseudo_labels(teacher_point_logits, cfg.semi.pseudo_threshold, ignore, cfg.semi.pseudo_class_share)
    pseudo_per_scan = pseudo.split([p.shape[0] for p in unlabeled])
    extra = {}
    if cfg.semi.oracle_labels:  # diagnostic: the scans' own labels instead of the teacher's
        pseudo_per_scan = [y.to(device) for y in batch["unlabeled_labels"]]
        truth, kept = torch.cat(pseudo_per_scan), pseudo != ignore
        scored = kept & (truth != ignore)
        # accuracy of the teacher's confident pseudo-labels the oracle replaced (logged, not trained on); NaN when
        # the teacher is confident on no labelled point (the mean of an empty set; the log window then reads NaN)
        extra["pseudo_accuracy"] = (pseudo[scored] == truth[scored]).float().mean()

    # LaserMix: 2 mixed scans per (labeled, unlabeled) pair, area count seeded by (seed, step, slot)
    mixed, mixed_targets = [], []
    for slot, (p_a, y_a, p_b, y_b) in zip(batch["slots"], zip(labeled, targets, unlabeled, pseudo_per_scan)):
        generator = torch.Generator().manual_seed(_seed(cfg.seed, _MIX, int(batch["step"]), slot))
        m1, l1, m2, l2 = lasermix(p_a, y_a, p_b, y_b, cfg.semi.num_areas_choices, pitch_range(cfg), generator=generator)
        mixed += [m1, m2]
        mixed_targets += [l1, l2]

    # student: one forward over labeled (B), mixed (2B) and unlabeled (B) scans, logits split back
    scans = labeled + mixed + unlabeled
    if voxel:
        out = student(scans, voxel_output=True)  # voxel rows sorted by scan
        unlabeled_target = torch.full((sum(p.shape[0] for p in unlabeled),), ignore, dtype=torch.int64, device=device)
        target = voxel_targets(
            torch.cat(targets + mixed_targets + [unlabeled_target]), out.inverse, len(out.logits), ignore
        )
        per_scan = torch.bincount(out.batch, minlength=len(scans)).tolist()  # voxels of each scan
        b = len(labeled)
        counts = [sum(per_scan[:b]), sum(per_scan[b : 3 * b]), sum(per_scan[3 * b :])]
        sup_logits, mix_logits, unl_logits = out.logits.split(counts)  # unl rows match the teacher's voxels
        sup_target, mix_target, _ = target.split(counts)
    else:
        logits = student(scans)  # (sum of all points, K)
        counts = [sum(p.shape[0] for p in group) for group in (labeled, mixed, unlabeled)]
        sup_logits, mix_logits, unl_logits = logits.split(counts)
        sup_target, mix_target = torch.cat(targets), torch.cat(mixed_targets)
    loss_sup = segmentation_loss(sup_logits, sup_target, cfg.loss, ignore, class_weight)["loss"]
    loss_mix = segmentation_loss(mix_logits, mix_target, cfg.loss, ignore, class_weight)["loss"]
    loss_mt = consistency_loss(unl_logits, teacher_logits)
    return {
        "loss": total_loss(loss_sup, loss_mix, loss_mt, cfg.semi, step=int(batch["step"]) - cfg.semi.burn_in_steps),
        "loss_sup": loss_sup,
        "loss_mix": loss_mix,
        "loss_mt": loss_mt,
        "pseudo_kept": (pseudo != ignore).float().mean(),  # share of confident pseudo-labels
        **extra,
    }


def in_burn_in(cfg: SemiConfig, step: int) -> bool:
    """Whether step `step` is a supervised burn-in step (no unlabeled scans, no teacher forward)."""
    return step < cfg.burn_in_steps


@torch.no_grad()
def update_teacher(teacher: nn.Module, student: nn.Module, cfg: SemiConfig, step: int) -> None:
    """EMA of the parameters after optimiser step `step`; BatchNorm buffers copied when bn_mode == copy_student.

    During burn-in the teacher is the student: its parameters and BatchNorm statistics are copied (Unbiased
    Teacher: the burnt-in student becomes the teacher; it never runs forward before the first mean-teacher step).
    """
    burn_in = in_burn_in(cfg, step)
    ema_update(teacher, student, 0.0 if burn_in else cfg.ema_decay)
    if cfg.bn_mode == "copy_student" or burn_in:
        copy_buffers(teacher, student)
