"""How generated scans are sampled: one `SamplingSettings` read by `u4d generate` (its flat keys sampler,
sampler_grid, steps, stage1_steps, stage1_mask_fraction, mean_start_below), `pipeline.generate_u4d`,
`pipeline.generate_baseline` and `GeneratedScans`, so the API and the CLI make the same scans.

The defaults are those of the shipped preset configs/u4d/generate_hdl64.yaml (tests/u4d_aug/test_sampling_settings.py
keeps them equal): DPM-Solver++(2M) SDE at 20 steps, 6 for stage 1 (the uncertain region), its mask capped at the
10 % of the pixels P_u covers, and each net's stored training mean as x̂0 below log-SNR -10 (`pipeline.MeanStart`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from u4d_aug.errors import InputError
from u4d_aug.sampling import SAMPLER_NAMES, Grid, SamplerName, check_grid


@dataclass(frozen=True)
class SamplingSettings:
    """The sampler and its options for every stage of a generator (configs/u4d/generate_hdl64.yaml)."""

    # u4d_aug.sampling.sample: ddpm (ancestral, R2DM's), ddim, dpmpp2m (DPM-Solver++(2M)) or its SDE form
    sampler: SamplerName = "dpmpp2m-sde"
    # `u4d generate`'s sampler_grid; "logsnr": steps uniform in log-SNR (dpmpp2m and dpmpp2m-sde only)
    grid: Grid = "time"
    steps: int = 20
    stage1_steps: int | None = 6  # U4D's stage 1, which draws only the uncertain region; None = steps
    # U4D's stage-1 mask keeps at most this share of each frame's pixels (`pipeline.cap_mask`); None = no cap
    stage1_mask_fraction: float | None = 0.1
    # below this log-SNR x̂0 is the net's stored per-row training mean (`pipeline.MeanStart`); None = the net's own
    mean_start_below: float | None = -10.0

    def __post_init__(self) -> None:
        if self.sampler not in SAMPLER_NAMES:
            raise InputError(f"sampler: {self.sampler!r} is not one of {', '.join(map(repr, SAMPLER_NAMES))}")
        try:
            check_grid(self.sampler, self.grid)
        except ValueError as exc:
            raise InputError(f"grid: {exc}") from None
        if not _is_count(self.steps):
            raise InputError(f"steps: expected an integer >= 1, got {self.steps!r}")
        if self.stage1_steps is not None and not _is_count(self.stage1_steps):
            raise InputError(f"stage1_steps: expected an integer >= 1 or None (= steps), got {self.stage1_steps!r}")
        fraction = self.stage1_mask_fraction
        if fraction is not None and not (_is_number(fraction) and 0.0 < fraction <= 1.0):
            raise InputError(f"stage1_mask_fraction: expected a share in (0, 1] or None, got {fraction!r}")
        below = self.mean_start_below
        if below is not None and not (_is_number(below) and math.isfinite(below)):
            raise InputError(f"mean_start_below: expected a finite log-SNR or None, got {below!r}")


def _is_count(value: object) -> bool:
    """An int >= 1 (not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def _is_number(value: object) -> bool:
    """An int or float (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


DEFAULT_SAMPLING = SamplingSettings()  # the shipped preset's settings, each sampling function's default
