"""Range view: points <-> (depth, reflectance) images after R2DM `utils/lidar.py` (generation_protocols 1.1).

Rows follow the sensor's ring table ("beam": nearest ring elevation) or R2DM's fixed linear FOV ("linear");
columns use R2DM's azimuth convention `col = floor(((-atan2(y, x)/pi + 1)/2 mod 1) * W)`. The nearest point
wins each pixel (ties: the lower point index). Every projection keeps the per-point pixel index and the
per-pixel winner index, so any per-point value (label, entropy, probability) projects the same way.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.errors import InputError

__all__ = [
    "ROUGHNESS_DIRECTIONS",
    "ROW_MODES",
    "Projection",
    "RoughnessDirection",
    "RowMode",
    "decode_depth",
    "encode_depth",
    "image_roughness",
    "project",
    "project_batch",
    "ray_angles",
    "roundtrip_stats",
    "scatter_to_image",
    "to_image",
    "unproject",
]

RowMode = Literal["beam", "linear"]
ROW_MODES: tuple[str, ...] = ("beam", "linear")
RoughnessDirection = Literal["ring", "vertical"]
ROUGHNESS_DIRECTIONS: tuple[str, ...] = ("ring", "vertical")

_LOW_32_BITS = 0xFFFFFFFF
NO_RETURN = -0.99  # encoded depth below this is an empty pixel (`to_image` writes -1 there)
_RANGE_TOLERANCE = 1e-3  # relative slack on [min_range, max_range] when decoding: float32 log/exp round trip


@dataclass
class Projection:
    """Points projected to an (H, W) image; batched projections carry a leading B on the image fields."""

    depth: Tensor  # (H, W) | (B, H, W) float32 metres of the winning point, 0 where no return
    reflectance: Tensor  # (H, W) | (B, H, W) float32 intensity of the winning point, 0 where no return
    mask: Tensor  # (H, W) | (B, H, W) bool, True where a point was projected
    pixel: Tensor  # (N,) int64 flat pixel index (b*H*W + row*W + col), -1 if out of range
    winner: Tensor  # (H, W) | (B, H, W) int64 index of the shown point (concatenated points), -1 if none
    offsets: Tensor  # (B+1,) int64 start of each scan in the concatenated points; (2,) = [0, N] for one scan


def _check_row_mode(row_mode: str) -> None:
    if row_mode not in ROW_MODES:
        raise InputError(f"row_mode {row_mode!r} is not one of {', '.join(ROW_MODES)}")


def _check_beam_height(sensor: Sensor, height: int) -> None:
    if height != sensor.num_rings:
        raise InputError(
            f"row_mode 'beam' needs height == number of rings ({sensor.num_rings}) of sensor "
            f"{sensor.name!r}, got {height}; use row_mode 'linear' for other heights"
        )


def encode_depth(depth: Tensor, max_depth: float) -> Tensor:
    """R2DM log-depth: log2(d + 1) / log2(d_max + 1) mapped to [-1, 1]; d = 0 (no return) gives -1."""
    x01 = torch.log2(depth.clamp(min=0.0) + 1.0) / math.log2(max_depth + 1.0)
    return (x01 * 2.0 - 1.0).clamp(-1.0, 1.0)


def decode_depth(x: Tensor, max_depth: float) -> Tensor:
    """Inverse of `encode_depth` (R2DM `revert_depth`): d = 2^(x01 log2(d_max + 1)) - 1, x01 = (x + 1) / 2."""
    x01 = (x.clamp(-1.0, 1.0) + 1.0) / 2.0
    return torch.exp2(x01 * math.log2(max_depth + 1.0)) - 1.0


def ray_angles(
    sensor: Sensor | str,
    height: int | None = None,
    width: int | None = None,
    row_mode: RowMode = "beam",
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Ray angles at bin centres: elevation (H,) radians top row first, azimuth atan2(y, x) (W,) radians."""
    sensor = _as_sensor(sensor)
    height = sensor.height if height is None else height
    width = sensor.width if width is None else width
    _check_row_mode(row_mode)
    if row_mode == "beam":
        _check_beam_height(sensor, height)
        elevation = torch.tensor(sensor.elevations_deg, dtype=torch.float64)
    else:
        fov = sensor.fov_up_deg - sensor.fov_down_deg
        elevation = sensor.fov_up_deg - fov * (torch.arange(height, dtype=torch.float64) + 0.5) / height
    # column j covers u = ((-az/pi + 1)/2 mod 1) in [j/W, (j+1)/W); centre (j+0.5)/W -> az = pi(1 - 2 u)
    azimuth = math.pi * (1.0 - 2.0 * (torch.arange(width, dtype=torch.float64) + 0.5) / width)
    return (
        torch.deg2rad(elevation).to(device=device, dtype=torch.float32),
        azimuth.to(device=device, dtype=torch.float32),
    )


@functools.lru_cache(maxsize=32)
def _row_table(sensor: Sensor, height: int, row_mode: str, device: str) -> tuple[float, float, Tensor, Tensor]:
    """Lookup table replacing a binary search: rows from sin(elevation) with one gather and one compare.

    Row boundaries (sin of the elevations between rows, ascending) are put in cells of a uniform grid by the
    same float32 expression that `_rows` applies to points; the expression is monotonic, so a point is above
    every boundary of a lower cell, below every boundary of a higher cell, and compared with the (at most one)
    boundary of its own cell. Returns (lo, inv_width, row_of_cell (G,), boundary_of_cell (G,)).
    """
    if row_mode == "beam":
        ascending = np.deg2rad(np.asarray(sensor.elevations_deg[::-1], dtype=np.float64))
        edges = (ascending[1:] + ascending[:-1]) / 2.0  # nearest ring: midpoints between neighbouring rings
    else:  # R2DM: row = floor((fov_up - elevation) / fov * H), so row k ends at fov_up - fov * k / H
        fov = sensor.fov_up_deg - sensor.fov_down_deg
        edges = np.deg2rad(sensor.fov_up_deg - fov * np.arange(height - 1, 0, -1) / height)
    boundaries = torch.from_numpy(np.sin(edges)).float()  # (H-1,) ascending
    if len(boundaries) == 0:
        return (
            0.0,
            1.0,
            torch.zeros(1, dtype=torch.int64, device=device),
            torch.full((1,), math.inf, device=device),
        )
    gap = float(torch.diff(boundaries).min()) if len(boundaries) > 1 else 1.0
    num_cells = max(int(math.ceil(float(boundaries[-1] - boundaries[0]) / gap)) * 2, 4)
    for _ in range(30):
        cell_width = float(boundaries[-1] - boundaries[0]) / num_cells or 1e-3
        lo, inv_width = float(boundaries[0]) - cell_width, 1.0 / cell_width
        cell = _cells(boundaries, lo, inv_width, num_cells + 2)
        if bool((torch.diff(cell) > 0).all()):
            break
        num_cells *= 2
    else:
        raise InputError(f"sensor {sensor.name!r}: row boundaries too close to tabulate")
    num_cells += 2
    below = torch.zeros(num_cells, dtype=torch.int64).index_add_(0, cell, torch.ones_like(cell)).cumsum(0)
    count_below = torch.cat([below.new_zeros(1), below[:-1]])  # boundaries in strictly lower cells
    boundary_of_cell = torch.full((num_cells,), math.inf).index_copy_(0, cell, boundaries)
    row_of_cell = (height - 1) - count_below
    return lo, inv_width, row_of_cell.to(device), boundary_of_cell.to(device)


def _cells(sin_elevation: Tensor, lo: float, inv_width: float, num_cells: int) -> Tensor:
    # NaN (point at the origin or non-finite; dropped later as out of range) -> 0 so the gather stays valid
    return (sin_elevation - lo).mul_(inv_width).nan_to_num_(0.0).floor_().clamp_(0, num_cells - 1).long()


def _rows(sin_elevation: Tensor, sensor: Sensor, height: int, row_mode: str) -> Tensor:
    """Row index (N,) int64 from sin(elevation) = z / depth (monotonic in elevation: no asin/atan2)."""
    lo, inv_width, row_of_cell, boundary_of_cell = _row_table(sensor, height, row_mode, str(sin_elevation.device))
    cell = _cells(sin_elevation, lo, inv_width, len(row_of_cell))
    return row_of_cell.index_select(0, cell) - (sin_elevation > boundary_of_cell.index_select(0, cell)).long()


def _columns(x: Tensor, y: Tensor, width: int) -> Tensor:
    """Column index (N,) int64, R2DM convention: col = floor(((-atan2(y, x)/pi + 1)/2 mod 1) * W)."""
    u = torch.atan2(y, x).mul_(-0.5 / math.pi).add_(0.5).remainder_(1.0)
    return u.mul_(width).floor_().clamp_(0, width - 1).long()  # clamp: float rounding can give u*W == W


def _project_flat(
    points: Tensor,
    batch: Tensor | None,
    num_scans: int,
    sensor: Sensor,
    height: int,
    width: int,
    row_mode: str,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Core of `project`/`project_batch`: concatenated points (N, 4), scan index `batch` (N,) or None."""
    _check_row_mode(row_mode)
    if height < 1 or width < 1:
        raise InputError(f"range image size must be at least 1x1, got height {height}, width {width}")
    if row_mode == "beam":
        _check_beam_height(sensor, height)
    if points.ndim != 2 or points.shape[1] < 4:
        raise InputError(f"points must have shape (N, 4), got {tuple(points.shape)}")
    num_points, num_pixels = points.shape[0], num_scans * height * width
    if num_points >= 2**31 - 1:
        raise InputError(f"too many points for one projection call: {num_points}")
    # (N, 4) -> contiguous columns; one spare zero column at index N for empty pixels to gather
    source = torch.empty(2, num_points + 1, dtype=torch.float32, device=points.device)  # [depth, intensity]
    source[:, num_points] = 0.0
    depth, intensity = source[0, :num_points], source[1, :num_points]
    x, y, z = (points[:, c].float().contiguous() for c in range(3))
    intensity.copy_(points[:, 3])
    torch.sqrt(x * x + y * y + z * z, out=depth)  # (N,)
    in_range = (depth >= sensor.min_range) & (depth <= sensor.max_range)  # NaN compares False
    pixel = _rows(z / depth, sensor, height, row_mode).mul_(width).add_(_columns(x, y, width))  # (N,)
    if batch is not None:
        pixel.add_(batch * (height * width))
    out_of_range = ~in_range
    pixel.masked_fill_(out_of_range, num_pixels)  # out of range -> one spare slot past the image

    # Nearest wins: one amin over key = (float32 depth bits << 32) | point index. Non-negative float32 bit
    # patterns order like the floats, so the smallest key is the nearest point and ties go to the lower index.
    # The empty value decodes to index N, which gathers the spare zero column of `source`.
    index = torch.arange(num_points, device=points.device, dtype=torch.int64)
    key = depth.view(torch.int32).long().bitwise_left_shift_(32).bitwise_or_(index)
    best = torch.full((num_pixels + 1,), (0x7FFFFFFF << 32) | num_points, dtype=torch.int64, device=points.device)
    best.scatter_reduce_(0, pixel, key, reduce="amin", include_self=True)
    winner = best[:num_pixels].bitwise_and_(_LOW_32_BITS)  # (B*H*W,) point index, N where empty
    images = source.index_select(1, winner)  # (2, B*H*W) depth, intensity of the winners
    mask = winner < num_points
    winner.masked_fill_(~mask, -1)
    pixel.masked_fill_(out_of_range, -1)
    shape = (num_scans, height, width)
    return images[0].view(shape), images[1].view(shape), mask.view(shape), pixel, winner.view(shape)


def _as_points(points: Tensor | np.ndarray) -> Tensor:
    """(N, >= 4) points as a tensor; anything else is an InputError naming `points`."""
    points = torch.as_tensor(points) if isinstance(points, np.ndarray) else points
    if not isinstance(points, Tensor) or points.ndim != 2 or points.shape[1] < 4:
        got = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
        raise InputError(f"points: expected shape (N, 4) (x, y, z, intensity), got {got}")
    return points


def _as_sensor(sensor: Sensor | str) -> Sensor:
    """A Sensor, or one named ('hdl64', 'hdl32', ...: `data.sensors.get_sensor`)."""
    if isinstance(sensor, str):
        return get_sensor(sensor)
    if not isinstance(sensor, Sensor):
        raise InputError(f"sensor: expected a Sensor or a sensor name such as 'hdl64', got {type(sensor).__name__}")
    return sensor


def project(
    points: Tensor | np.ndarray,
    sensor: Sensor | str,
    height: int | None = None,
    width: int | None = None,
    row_mode: RowMode = "beam",
) -> Projection:
    """Project one scan (N, 4) [x, y, z, intensity] to an (H, W) range image; nearest point wins a pixel.
    `sensor` may be given by name ('hdl64')."""
    scan, spec = _as_points(points), _as_sensor(sensor)
    height = spec.height if height is None else height
    width = spec.width if width is None else width
    depth, reflectance, mask, pixel, winner = _project_flat(scan, None, 1, spec, height, width, row_mode)
    offsets = torch.tensor([0, scan.shape[0]], dtype=torch.int64, device=scan.device)
    return Projection(depth[0], reflectance[0], mask[0], pixel, winner[0], offsets)


def project_batch(
    points: list[Tensor] | list[np.ndarray],
    sensor: Sensor | str,
    height: int | None = None,
    width: int | None = None,
    row_mode: RowMode = "beam",
) -> Projection:
    """Project B scans at once (concatenated with batch offsets) to (B, H, W); equals `project` per scan."""
    if len(points) == 0:
        raise InputError("project_batch needs at least one scan")
    scans, spec = [_as_points(p) for p in points], _as_sensor(sensor)
    height = spec.height if height is None else height
    width = spec.width if width is None else width
    device = scans[0].device
    counts = torch.tensor([s.shape[0] for s in scans], dtype=torch.int64, device=device)
    batch = torch.repeat_interleave(torch.arange(len(scans), device=device), counts)  # (N,)
    offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])  # (B+1,)
    depth, reflectance, mask, pixel, winner = _project_flat(
        torch.cat(scans), batch, len(scans), spec, height, width, row_mode
    )
    return Projection(depth, reflectance, mask, pixel, winner, offsets)


def to_image(projection: Projection, sensor: Sensor) -> Tensor:
    """(2, H, W) or (B, 2, H, W) [depth, reflectance] in [-1, 1], -1 for no return (R2DM preprocessing)."""
    # empty pixels hold depth 0 and reflectance 0, which both encode to -1
    depth = encode_depth(projection.depth, sensor.max_range)
    reflectance = projection.reflectance.clamp(0.0, 1.0) * 2.0 - 1.0
    return torch.stack([depth, reflectance], dim=-3)


def image_roughness(images: Tensor, direction: RoughnessDirection = "ring") -> tuple[float, float]:
    """(mean |encoded depth step| between adjacent returns, share of pixels with a return) of images (..., 2, H, W):
    the surface noise of a range image along a ring ("ring": horizontally adjacent pixels, one beam's neighbouring
    azimuths) or down a column ("vertical": vertically adjacent pixels, neighbouring beams at one azimuth); real
    64x1024 scans of the simulated world: ring ~0.007, share ~0.87."""
    depth = images[..., 0, :, :]
    valid = depth > NO_RETURN
    if direction == "ring":
        both = valid[..., 1:] & valid[..., :-1]
        steps = (depth[..., 1:] - depth[..., :-1]).abs()
    elif direction == "vertical":
        both = valid[..., 1:, :] & valid[..., :-1, :]
        steps = (depth[..., 1:, :] - depth[..., :-1, :]).abs()
    else:
        raise InputError(f"roughness direction {direction!r} is not one of {', '.join(ROUGHNESS_DIRECTIONS)}")
    rough = float(steps[both].mean()) if both.any() else float("nan")
    return rough, float(valid.float().mean())


def unproject(
    image: Tensor, sensor: Sensor, row_mode: RowMode = "beam", mask: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Image (..., 2, H, W) in [-1, 1] -> points (..., H, W, 4) [x, y, z, reflectance] at bin-centre rays.

    Also returns valid (..., H, W) bool: decoded depth within the sensor range (1e-3 relative slack), and
    `mask` if given. Invalid pixels hold zeros. After R2DM `LiDARUtility.revert_depth` / `to_xyz`.
    """
    if image.ndim < 3 or image.shape[-3] != 2:
        raise InputError(f"image must have shape (..., 2, H, W), got {tuple(image.shape)}")
    height, width = image.shape[-2:]
    elevation, azimuth = ray_angles(sensor, height, width, row_mode, device=image.device)
    depth = decode_depth(image[..., 0, :, :].float(), sensor.max_range)  # (..., H, W)
    reflectance = (image[..., 1, :, :].float().clamp(-1.0, 1.0) + 1.0) / 2.0
    valid = (depth >= sensor.min_range * (1.0 - _RANGE_TOLERANCE)) & (
        depth <= sensor.max_range * (1.0 + _RANGE_TOLERANCE)
    )
    if mask is not None:
        valid = valid & mask.to(device=image.device, dtype=torch.bool)
    cos_el, sin_el = torch.cos(elevation)[:, None], torch.sin(elevation)[:, None]  # (H, 1)
    cos_az, sin_az = torch.cos(azimuth)[None, :], torch.sin(azimuth)[None, :]  # (1, W)
    points = torch.stack(
        [depth * cos_el * cos_az, depth * cos_el * sin_az, depth * sin_el.expand(height, width), reflectance],
        dim=-1,
    )
    points = torch.where(valid.unsqueeze(-1), points, torch.zeros((), device=image.device))
    return points, valid


def scatter_to_image(values: Tensor, projection: Projection, fill: float | int = 0) -> Tensor:
    """Per-point values (N, ...) -> (H, W, ...) or (B, H, W, ...) via the projection winners, else `fill`."""
    expected = int(projection.offsets[-1])
    if values.shape[0] != expected:
        raise InputError(f"values have {values.shape[0]} rows but the projection has {expected} points")
    winner = projection.winner.to(values.device)
    gathered = values[winner.clamp(min=0)]  # (..., H, W, *rest)
    keep = (winner >= 0).reshape(*winner.shape, *([1] * (values.ndim - 1)))
    return torch.where(keep, gathered, torch.full((), fill, dtype=values.dtype, device=values.device))


def roundtrip_stats(
    points: Tensor | np.ndarray,
    sensor: Sensor | str,
    height: int | None = None,
    width: int | None = None,
    row_mode: RowMode = "beam",
) -> dict[str, float | int]:
    """Project -> encode -> unproject; 3D error of every winning point vs its pixel's reconstruction."""
    points, sensor = _as_points(points).float(), _as_sensor(sensor)
    projection = project(points, sensor, height, width, row_mode)
    xyz_hat, valid = unproject(to_image(projection, sensor), sensor, row_mode, mask=projection.mask)
    shown = projection.winner[valid]  # (M,) winning point indices
    error = torch.linalg.vector_norm(xyz_hat[valid][:, :3] - points[shown, :3], dim=1).double()
    num_points = int(points.shape[0])
    return {
        "points": num_points,
        "kept_fraction": float(shown.numel() / max(num_points, 1)),
        "median_error_m": float(error.median()) if error.numel() else float("nan"),
        "p99_error_m": float(torch.quantile(error, 0.99)) if error.numel() else float("nan"),
    }
