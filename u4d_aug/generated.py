"""Scans generated on the fly for a training loop: an iterable of `ScanDataset`-like items, no bank on disk.

Sample i is drawn with its own generator seeded `seed + i` in fixed blocks of `batch_size` consecutive samples,
as `u4d generate` does, and sampled with the same `SamplingSettings` (`GenerateConfig.sampling()`), so the stream
yields the scans a bank of the same settings, seed and batch_size holds, in the same order (`seq`/`frame` name the
files that bank would have). Samples with no return at all are skipped, as a bank skips them. Under a `DataLoader`
with several workers, worker w takes blocks w, w + W, ... (no duplicates).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Literal

import torch
from torch.utils.data import IterableDataset, get_worker_info

from u4d_aug.bank import BANK_SEQUENCE, sequence_name
from u4d_aug.errors import InputError
from u4d_aug.pipeline import Loaded, generate_baseline, generate_u4d, load_generator, to_points
from u4d_aug.sampling_settings import DEFAULT_SAMPLING, SamplingSettings

__all__ = ["GeneratedScans"]

Mode = Literal["u4d", "baseline"]


def _loaded(net: Loaded | str | Path, i: int) -> Loaded:
    """nets[i]: a `load_generator` result as is, a checkpoint / weights path loaded here; else an InputError."""
    if isinstance(net, (str, Path)):
        return load_generator(net)
    if not (isinstance(net, tuple) and len(net) == 2 and isinstance(net[0], torch.nn.Module)):
        raise InputError(
            f"GeneratedScans: nets[{i}] is a {type(net).__name__}; expected load_generator(...) or a checkpoint path"
        )
    return net


class GeneratedScans(IterableDataset):
    """U4D (nets = [stage 1, stage 2]) or baseline (nets = [net]) scans: {points, labels None, seq, frame}; a net is
    `load_generator(...)`'s result or a checkpoint path.

    `num` samples (None: endless); a generator trained on L > 1 frames gives L scans per sample. `settings` as
    `u4d generate` reads them (default: configs/u4d/generate_hdl64.yaml's, whose mean start needs nets exported
    with their training means, `u4d export-weights --data-root`).
    """

    def __init__(
        self,
        mode: Mode,
        nets: Sequence[Loaded | str | Path],
        num: int | None = None,
        seed: int = 0,
        batch_size: int = 1,
        settings: SamplingSettings = DEFAULT_SAMPLING,
        frames: int | None = None,
    ) -> None:
        if mode == "u4d":
            needed = 2
        elif mode == "baseline":
            needed = 1
        else:
            raise InputError(f"GeneratedScans: mode {mode!r} is not one of 'u4d', 'baseline'")
        if len(nets) != needed:
            raise InputError(f"GeneratedScans: mode {mode} takes {needed} loaded net(s), got {len(nets)}")
        if (num is not None and num < 0) or batch_size < 1:
            raise InputError(f"GeneratedScans: need num >= 0, batch_size >= 1; got {num}, {batch_size}")
        self.mode = mode
        self.nets = [_loaded(net, i) for i, net in enumerate(nets)]
        self.num = num
        self.seed = seed
        self.batch_size = batch_size
        self.settings = settings
        _, cfg = self.nets[-1]
        self.frames = frames or cfg.frames

    def __iter__(self) -> Iterator[dict]:
        worker = get_worker_info()
        worker_id, workers = (worker.id, worker.num_workers) if worker is not None else (0, 1)
        starts = itertools.count(0, self.batch_size) if self.num is None else range(0, self.num, self.batch_size)
        for k, start in enumerate(starts):
            if k % workers != worker_id:
                continue
            stop = start + self.batch_size if self.num is None else min(start + self.batch_size, self.num)
            yield from self._block(list(range(start, stop)))

    def _block(self, block: list[int]) -> Iterator[dict]:
        """The scans of samples `block`, each drawn with the generator seeded seed + i."""
        generators = [torch.Generator().manual_seed(self.seed + i) for i in block]
        with torch.no_grad():
            x0 = self._sample(len(block), generators)  # (n, [L,] 2, H, W)
        _, cfg = self.nets[-1]
        clouds = to_points(x0, cfg.sensor, cfg.row_mode)  # n·L clouds, samples then frames
        for j, i in enumerate(block):
            for frame in range(self.frames):
                points = clouds[j * self.frames + frame]
                if len(points) == 0:
                    continue
                if self.frames == 1:
                    seq, name = BANK_SEQUENCE, f"{i:06d}"
                else:
                    seq, name = sequence_name(i), f"{frame:06d}"
                yield {"points": points, "labels": None, "seq": seq, "frame": name}

    def _sample(self, n: int, generators: list[torch.Generator]) -> torch.Tensor:
        if self.mode == "u4d":
            stage1, stage2 = self.nets
            result = generate_u4d(stage1, stage2, n, generators, self.settings, self.frames)
        else:
            result = generate_baseline(self.nets[0], n, generators, self.settings, self.frames)
        return result["x0"]
