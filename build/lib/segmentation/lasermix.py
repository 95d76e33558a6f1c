"""LaserMix: swap alternating inclination areas of two scans (Kong et al. 2023, `laser_mix_transform`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch


def pitch_areas(points: torch.Tensor, num_areas: int, pitch_range_deg: tuple[float, float]) -> torch.Tensor:
    """(N,) area index per point, 0 = top: pitch clamped into the range, n equal-width areas (LaserMix)."""
    down_deg, up_deg = pitch_range_deg
    if not down_deg < up_deg:
        raise ValueError(f"pitch_range_deg must be (down, up) with down < up; got {pitch_range_deg}")
    if num_areas < 1:
        raise ValueError(f"num_areas must be >= 1; got {num_areas}")
    down, up = math.radians(down_deg), math.radians(up_deg)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    # phi = atan2(z, sqrt(x^2 + y^2)), clamped so that points outside the range land in the top/bottom area
    phi = torch.atan2(z, torch.sqrt(x * x + y * y)).clamp(down + 1e-5, up - 1e-5)  # (N,)
    # edges = linspace(up, down, n + 1); area i covers (edges[i + 1], edges[i]]
    edges = torch.linspace(up, down, num_areas + 1, dtype=torch.float64).to(phi.dtype).to(phi.device)
    inner = edges[1:num_areas]  # (n - 1,) descending
    return (phi[:, None] <= inner[None, :]).sum(dim=1)  # number of inner edges at or above phi


def draw_num_areas(num_areas_choices: Sequence[int], generator: torch.Generator) -> int:
    """Number of areas for one scan pair, uniform over the choices (the only random draw of `lasermix`)."""
    if len(num_areas_choices) == 0:
        raise ValueError("num_areas_choices must not be empty")
    k = torch.randint(len(num_areas_choices), (1,), generator=generator, device=generator.device)
    return int(num_areas_choices[int(k)])


def lasermix(
    points_a: torch.Tensor,
    labels_a: torch.Tensor,
    points_b: torch.Tensor,
    labels_b: torch.Tensor,
    num_areas_choices: Sequence[int] = (3, 4, 5, 6),
    pitch_range_deg: tuple[float, float] = (-25.0, 3.0),
    *,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Two complementary LaserMix scans of a pair: mix1 = a's even areas + b's odd areas, mix2 = the rest.

    points_* are (N, C >= 3) in the sensor frame (after augmentation), labels_* (N,) ground truth or
    pseudo-labels; every input point goes to exactly one output with its own label. Within each output the
    points of `a` come first, then those of `b`, each in input order (upstream concatenates per area; the
    order is irrelevant once voxelized). `pitch_range_deg` = (fov_down, fov_up) of the sensor:
    SemanticKITTI (-25, 3), nuScenes (-30, 10).
    """
    for name, p, lab in (("a", points_a, labels_a), ("b", points_b, labels_b)):
        if p.ndim != 2 or p.shape[1] < 3 or lab.shape != (p.shape[0],):
            raise ValueError(
                f"points_{name} must be (N, C>=3) with labels_{name} (N,); got {tuple(p.shape)} and {tuple(lab.shape)}"
            )
    num_areas = draw_num_areas(num_areas_choices, generator)
    even_a = pitch_areas(points_a, num_areas, pitch_range_deg) % 2 == 0  # (N_a,)
    even_b = pitch_areas(points_b, num_areas, pitch_range_deg) % 2 == 0  # (N_b,)
    mix1_points = torch.cat([points_a[even_a], points_b[~even_b]])
    mix1_labels = torch.cat([labels_a[even_a], labels_b[~even_b]])
    mix2_points = torch.cat([points_a[~even_a], points_b[even_b]])
    mix2_labels = torch.cat([labels_a[~even_a], labels_b[even_b]])
    return mix1_points, mix1_labels, mix2_points, mix2_labels
