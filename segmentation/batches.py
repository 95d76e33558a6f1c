"""What a seg-train run trains on: the labeled scans (the labeled split), each step's batch, the val scans.

Exact resume rests here: the scans of step s, their point subsets and augmentations depend only on (seed, step,
slot in the global batch), so the global batch of a step does not depend on the number of ranks, DataLoader
workers or where the run was resumed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from segmentation.config import SegTrainConfig
from segmentation.data import augment, load_or_make_split, paste_instances, training_subset
from segmentation.semi import UnlabeledStream, in_burn_in, load_unlabeled
from u4d_aug.data.datasets import NuscenesScanDataset, ScanDataset, open_scans
from u4d_aug.distributed import DistInfo, barrier
from u4d_aug.errors import InputError
from u4d_aug.seeding import derived_seed

# seed domains, so that the streams of epochs and scans never share a seed (segmentation.train: 3, semi: 4-6)
_EPOCH, _SCAN = 1, 2


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
        split = (Path(cfg.out_dir), scans.entries, cfg.data.label_fraction, cfg.data.split_seed, cfg.data.split_mode)
        if info.is_main:  # rank 0 draws and writes the split file under OUT/splits; then every rank reads it
            load_or_make_split(*split)
        barrier()
        labeled, _ = load_or_make_split(*split)
        chosen = set(labeled)
        scans.entries = [entry for entry in scans.entries if entry in chosen]
    return scans


def val_scans(cfg: SegTrainConfig) -> ScanDataset | NuscenesScanDataset | None:
    """The labeled scans of data.val_sequences for the periodic evaluation (None: none configured or found)."""
    if cfg.data.val_sequences is None:
        return None
    scans = data_scans(cfg, cfg.data.val_sequences, labeled_only=True)
    return scans if len(scans) else None
