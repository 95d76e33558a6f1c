"""What a diffusion stage trains on: the range images of the scans (or L-frame windows) and the batch of each step.

Item i of `RangeImages` is scan i projected to x0 (2, H, W) with, for stages 1 and 2, its uncertain region x0_u
(2, H, W) and mask m_u (1, H, W) (U4D paper §2.1), for a cascade's detail net the scan's layout (its projection at
W / s columns) as x0_u on every s-th column and m_u those columns (`u4d_aug.cascade`); with `frames` = L > 1 the L
scans of window i, (L, C, H, W).
The scans of step s and the noise of step s depend only on (seed, step, rank) (`training_batch`), so a resumed
run draws what an uninterrupted one would; `crop_batch` cuts azimuth crops for training on part of the ring.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from u4d_aug.cascade import check_stride, place_columns
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
from u4d_aug.diffusion import CONDITIONED, stage1_count
from u4d_aug.errors import InputError
from u4d_aug.nn.unet import crop_columns
from u4d_aug.propagate import warp_frame0
from u4d_aug.range_view import project, to_image
from u4d_aug.seeding import derived_seed
from u4d_aug.stage import DiffusionTrainConfig
from u4d_aug.trajectory import relative_motion
from u4d_aug.uncertainty import load_probs, probs_path, uncertain_range_view

_BATCH, _NOISE = 1, 2  # streams of derived_seed


class RangeImages:
    """Item i = dict(x0 (2, H, W), x0_u (2, H, W), m_u (1, H, W)) of scan i; x0_u/m_u need probabilities.

    With cfg.frames = L > 1, item i stacks the L scans of window i of a `SequenceDataset` (one sequence,
    frame_stride apart): x0 (L, 2, H, W), x0_u (L, 2, H, W), m_u (L, 1, H, W); poses are not needed.
    x0_u and m_u are recomputed per scan for strategy 'random' (seeded by `generator`), cached otherwise.
    With cfg.propagated_share > 0 (stage 2, or u4d), a window drawn by `generator` with that probability is conditioned
    instead on frame 0 moved along its poses (x0_u, m_u of `propagate.warp_frame0`; frame 0 wholly known), unless
    `propagate` is False: a u4d batch's stage-1 windows, whose target is P_u itself (`make_batch`).
    With `encode` (a latent generator's) each scan's images are its latents instead (`latent.encode_item`).
    """

    def __init__(self, cfg: DiffusionTrainConfig, encode: Callable[[dict], dict] | None = None) -> None:
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
            with_poses = cfg.net.pose_dim > 0 or cfg.propagated_share > 0
            self.windows = open_sequences(
                cfg.data_root, cfg.frames, cfg.sequences, cfg.frame_stride, with_poses, *layout
            )
        self.needs_probs = cfg.diffusion.stage in ("stage1", "stage2", "u4d") and cfg.uncertainty.strategy != "none"
        if self.needs_probs and not cfg.probs_root:
            raise InputError(
                f"probs_root: stage {cfg.diffusion.stage} needs the probability files of `u4d seg-predict`"
            )
        self.cache: dict[tuple[str, str], dict[str, Tensor]] = {}
        # a latent generator's: a scan's images -> their latents (`latent.encode_item`), computed once and cached
        self.encode = encode

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

    def __getitem__(
        self, index: int, generator: torch.Generator | None = None, propagate: bool = True
    ) -> dict[str, Tensor]:
        seq, frames = self.window(index)
        if self.windows is None:
            return self.scan_images(seq, frames[0], generator)
        items = [self.scan_images(seq, frame, generator) for frame in frames]
        out = {key: torch.stack([item[key] for item in items]) for key in items[0]}  # (L, C, H, W) each
        start = self.windows.windows[index][1]
        positions = list(range(start, start + self.cfg.frames * self.cfg.frame_stride, self.cfg.frame_stride))
        if self.cfg.net.pose_dim:  # the ego motion of the window's frames, (L, 4) in the first frame's sensor frame
            out["motion"] = torch.from_numpy(relative_motion(self.windows.poses[seq][positions]))
        share = self.cfg.propagated_share if propagate else 0.0
        if share > 0 and generator is not None and float(torch.rand((), generator=generator)) < share:
            poses = self.windows.poses[seq][positions]  # (L, 4, 4)
            out["x0_u"], out["m_u"] = warp_frame0(out["x0"][0], poses, self.sensor, self.cfg.row_mode)
        return out

    def scan_images(self, seq: str, frame: str, generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """x0 (2, H, W) and, for stages 1, 2 and detail, x0_u (2, H, W), m_u (1, H, W) of one scan (cached)."""
        if (seq, frame) in self.cache:
            return self.cache[(seq, frame)]
        cfg = self.cfg
        points = torch.from_numpy(self.scans.load_points(seq, frame))
        x0 = to_image(project(points, self.sensor, cfg.height, cfg.width, cfg.row_mode), self.sensor)
        out = {"x0": x0}
        if cfg.diffusion.stage == "detail":  # the condition: the scan's layout, its projection at width / s columns
            low_width = check_stride(cfg.width, cfg.detail_stride)
            x_low = to_image(project(points, self.sensor, cfg.height, low_width, cfg.row_mode), self.sensor)
            out["x0_u"], out["m_u"] = place_columns(x_low, cfg.detail_stride)
        elif cfg.diffusion.stage != "baseline":
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
        if self.encode is not None:
            out = self.encode(out)
        if cfg.cache_images and cfg.uncertainty.strategy != "random":
            self.cache[(seq, frame)] = out
        return out


def row_mean(cfg: DiffusionTrainConfig, key: str = "x0", count: int = 32, seed: int = 0) -> Tensor:
    """(C, H, 1) mean of the `key` images (x0, or x0_u for stage 1) of `count` evenly spaced training items, over
    items, frames and columns: the MMSE estimate of a range image at vanishing SNR, per row (`sampling.mean_start`).
    `seed` draws P_u where the net's uncertainty strategy is random (the selection ablation)."""
    stacked = mean_images(cfg, key, count, seed)  # (K·L, C, H, W)
    return stacked.mean(dim=(0, 3)).unsqueeze(-1)


def mean_images(cfg: DiffusionTrainConfig, key: str = "x0", count: int = 32, seed: int = 0) -> Tensor:
    """(K·L, C, H, W) the `key` images of `count` evenly spaced training items, their frames unfolded (`row_mean`)."""
    cfg = dataclasses.replace(cfg, propagated_share=0.0)  # the mean of P_u (or x0), never of a propagated frame 0
    if key == "x0":  # full scans: no uncertainty (and no probability files, nor a stage-2 condition) needed
        baseline = dataclasses.replace(cfg.diffusion, stage="baseline", cond_noise=0.0)
        cfg = dataclasses.replace(cfg, diffusion=baseline)
    images = RangeImages(cfg)
    step = max(1, len(images) // count)
    generator = torch.Generator().manual_seed(seed)
    picked = [images.__getitem__(i, generator)[key] for i in range(0, len(images), step)[:count]]
    stacked = torch.stack(picked)  # (K, [L,] C, H, W)
    return stacked.reshape(-1, *stacked.shape[-3:])


def row_mean_key(cfg: DiffusionTrainConfig, role: str | None = None) -> str:
    """The images a net's mean start is the mean of: x0_u (the uncertain region) for stage 1 (a u4d net's stage-1
    role), x0 otherwise."""
    stage = cfg.diffusion.stage
    return "x0_u" if stage == "stage1" or (stage == "u4d" and role == "stage1") else "x0"


def net_row_mean(
    cfg: DiffusionTrainConfig, data_root: str = "", probs_root: str = "", role: str | None = None, encode=None
) -> tuple[Tensor, dict]:
    """`row_mean` of the images a net learns (x0_u for stage 1 or a u4d net's stage-1 `role`, x0 otherwise) from its
    training scans, or from `data_root` / `probs_root` when set, and where it was read: {key, data_root, sequences[,
    probs_root]}. A latent generator passes `encode` (images (N, C, H, W) -> latents (N, C_z, h, w)): the mean is
    then its latents' (C_z, h, 1)."""
    key = row_mean_key(cfg, role)
    cfg = dataclasses.replace(cfg, data_root=data_root or cfg.data_root, probs_root=probs_root or cfg.probs_root)
    source = {"key": key, "data_root": cfg.data_root, "sequences": cfg.sequences}
    if key == "x0_u":
        source["probs_root"] = cfg.probs_root
    if encode is None:
        return row_mean(cfg, key), source
    latents = torch.cat([encode(chunk) for chunk in mean_images(cfg, key).split(8)])
    return latents.mean(dim=(0, 3)).unsqueeze(-1), source | {"latent": True}


def batch_indices(step: int, rank: int, num_scans: int, batch_size: int, seed: int) -> list[int]:
    """This rank's scan indices of `step`: uniform with replacement from a (seed, step, rank) stream."""
    rng = np.random.default_rng(derived_seed(seed, _BATCH, step, rank))
    return rng.integers(0, num_scans, batch_size).tolist()


def make_batch(
    images: RangeImages, indices: list[int], generator: torch.Generator, device: torch.device, stage1_items: int = 0
) -> dict:
    """Stack the items of `indices` into (B, [L,] C, H, W) tensors on `device`; the first `stage1_items` (a u4d
    batch's stage-1 samples, `diffusion.stage1_count`) keep their own P_u, never the propagated condition."""
    items = [images.__getitem__(i, generator, position >= stage1_items) for position, i in enumerate(indices)]
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
    """(x0, cond, m_u) of GaussianDiffusion.forward: stage 1 learns x0 := x0_u; stage 2, u4d and detail read x0_u,
    m_u (a detail net's: the layout's columns)."""
    if stage == "stage1":
        return batch["x0_u"], None, batch["m_u"]
    if stage in CONDITIONED:
        return batch["x0"], batch["x0_u"], batch["m_u"]
    return batch["x0"], None, None


def crop_loss_weight(cfg: DiffusionTrainConfig, device: torch.device) -> Tensor | None:
    """(crop_width,) column weights of the losses: 0 on the `crop_margin` columns at each edge of a crop, else 1
    (None: no margin)."""
    if not cfg.crop_margin:
        return None
    weight = torch.ones(cfg.crop_width, device=device)
    weight[: cfg.crop_margin] = 0.0
    weight[-cfg.crop_margin :] = 0.0
    return weight


def training_batch(
    images: RangeImages, cfg: DiffusionTrainConfig, step: int, rank: int, device: torch.device
) -> tuple[dict[str, Tensor], Tensor | None, torch.Generator]:
    """This rank's batch of `step` on `device`, its azimuth crop offsets (None: the full panorama) and the generator
    of (seed, step, rank) that drew them, which then draws the step's noise."""
    generator = torch.Generator().manual_seed(derived_seed(cfg.seed, _NOISE, step, rank))
    indices = batch_indices(step, rank, len(images), cfg.batch_size, cfg.seed)
    stage1_items = stage1_count(len(indices), cfg.diffusion.stage1_share) if cfg.diffusion.stage == "u4d" else 0
    batch = make_batch(images, indices, generator, device, stage1_items)
    offsets = crop_offsets(len(indices), cfg, generator)
    if offsets is not None:
        batch = crop_batch(batch, offsets, cfg.crop_width)
    return batch, offsets, generator
