"""Controlled corruptions of one real scan for the metric-validity check
(`benchmarks/metric_validity.py`).

Each function takes one scan (N, 4) [x, y, z, reflectance] float32, a `level` in [0, 1] (0: the scan unchanged,
bit for bit) and an `rng`, and returns a new float32 scan with each point's reflectance kept. A point's ring and
azimuth column are the pixel `range_view.project` gives its ray at the sensor's own H x W in row mode "beam" (the
nearest ring elevation), so the rings and columns are those of the 64 x 1024 image a generator makes. The random
draws do not depend on `level`: with one seed the corruptions nest (the rings dropped at 0.25 are among those dropped
at 0.5, the noise at 0.5 is the noise at 1 halved), so a metric's curve over the levels is not a new draw per level.

- depth_noise: every point moves along its ray, range r -> r (1 + level * DEPTH_NOISE * z), z ~ N(0, 1) per point
  (at level 1 the range error has a std of 10 % of the range; the factor is clipped at 0.01 so no point crosses the
  sensor).
- smeared_walls: the points above the local ground (`structure.above_ground`: walls, poles, cars, trees) are smeared
  along their rays in a share `level` of azimuth blocks of SMEAR_BLOCK columns (4 of 1024: 1.4 degrees): in a chosen
  block, each such point's range is r -> r (1 + SMEAR * u), u ~ U(-1, 1) per point, so the block's stretch of wall
  becomes a radial streak from 0.5 r to 1.5 r (the "stars" of a generator whose wall depths disagree down a column);
  the ground and the other blocks stay as they are.
- dropped_rows: the points of round(level * MAX_DROPPED * rings) rings, chosen by rng, are removed (a generator that
  leaves whole rows empty); at level 1 that is 48 of the 64 rings, not all of them: an empty scan has no score.
- swapped_columns: round(level * W / 2) random pairs of azimuth columns (of W = 1024) trade places: each point of
  one column is rotated about z by the difference of the two columns' centre azimuths (`range_view.ray_angles`),
  so a share ~level of the points sits at another azimuth with its range, height and reflectance.
"""

from __future__ import annotations

import numpy as np

from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.errors import InputError
from u4d_aug.metrics.structure import above_ground
from u4d_aug.range_view import project, ray_angles

CORRUPTIONS = ("depth_noise", "smeared_walls", "dropped_rows", "swapped_columns")
DEPTH_NOISE = 0.10  # std of the relative range error at level 1
MIN_RANGE_FACTOR = 0.01  # a noisy range is clipped to at least this share of the true one (never through the sensor)
SMEAR = 0.5  # a smeared point's range goes to r (1 + SMEAR u), u ~ U(-1, 1)
SMEAR_BLOCK = 4  # azimuth columns per smeared block
MAX_DROPPED = 0.75  # share of the rings dropped at level 1


def _check(points: np.ndarray, level: float, where: str) -> np.ndarray:
    """(N, 4) float32 copy of `points`; an InputError for another shape or a level outside [0, 1]."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise InputError(f"{where}: expected points of shape (N, 4) (x, y, z, reflectance), got {points.shape}")
    if not 0.0 <= level <= 1.0:
        raise InputError(f"{where}: level must be in [0, 1], got {level}")
    return points.astype(np.float32, copy=True)


def ray_cells(points: np.ndarray, sensor: Sensor) -> tuple[np.ndarray, np.ndarray]:
    """(N,) ring (row) and (N,) azimuth column of each point's ray in the sensor's H x W beam-row image; -1 for a
    point at the origin. The ray is projected at mid-range, so points outside the sensor's range get a cell too."""
    xyz = points[:, :3].astype(np.float64)
    norm = np.linalg.norm(xyz, axis=1, keepdims=True)  # (N, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rays = xyz / norm * (sensor.min_range + sensor.max_range) / 2.0  # NaN at the origin: no pixel
    on_rays = np.concatenate([rays, np.zeros((len(points), 1))], 1).astype(np.float32)
    pixel = project(on_rays, sensor, sensor.num_rings, sensor.width, "beam").pixel.numpy()  # (N,) -1: none
    rows = np.where(pixel >= 0, pixel // sensor.width, -1)
    cols = np.where(pixel >= 0, pixel % sensor.width, -1)
    return rows, cols


def _scale_ranges(points: np.ndarray, factor: np.ndarray, where: np.ndarray) -> np.ndarray:
    """`points` with x, y, z of the points `where` (N,) bool multiplied by their `factor` (N,) (along the ray)."""
    out = points.copy()
    out[where, :3] = (points[where, :3].astype(np.float64) * factor[where, None]).astype(np.float32)
    return out


def depth_noise(points: np.ndarray, level: float, rng: np.random.Generator) -> np.ndarray:
    """Each point moved along its ray: r -> r (1 + level * DEPTH_NOISE * z), z ~ N(0, 1), clipped at 1 % of r."""
    points = _check(points, level, "depth_noise")
    z = rng.standard_normal(len(points))  # (N,)
    factor = np.maximum(1.0 + level * DEPTH_NOISE * z, MIN_RANGE_FACTOR)
    return _scale_ranges(points, factor, np.ones(len(points), dtype=bool))  # level 0: x * 1.0, exact


def smeared_walls(
    points: np.ndarray, level: float, rng: np.random.Generator, sensor: Sensor | str = "hdl64"
) -> np.ndarray:
    """The above-ground points of a share `level` of SMEAR_BLOCK-column azimuth blocks spread along their rays:
    r -> r (1 + SMEAR u), u ~ U(-1, 1) per point (radial streaks, a generator's "stars")."""
    points, sensor = _check(points, level, "smeared_walls"), get_sensor(sensor)
    num_blocks = -(-sensor.width // SMEAR_BLOCK)
    chosen = rng.permutation(num_blocks)[: round(level * num_blocks)]  # nested over levels: a prefix of one order
    u = rng.uniform(-1.0, 1.0, len(points))  # (N,)
    if len(chosen) == 0 or len(points) == 0:
        return points
    _, cols = ray_cells(points, sensor)
    smeared = np.isin(cols // SMEAR_BLOCK, chosen) & (cols >= 0) & above_ground(points)
    return _scale_ranges(points, 1.0 + SMEAR * u, smeared)


def dropped_rows(
    points: np.ndarray, level: float, rng: np.random.Generator, sensor: Sensor | str = "hdl64"
) -> np.ndarray:
    """The scan without the points of round(level * MAX_DROPPED * rings) of the sensor's rings, chosen by `rng`."""
    points, sensor = _check(points, level, "dropped_rows"), get_sensor(sensor)
    dropped = rng.permutation(sensor.num_rings)[: round(level * MAX_DROPPED * sensor.num_rings)]
    if len(dropped) == 0 or len(points) == 0:
        return points
    rows, _ = ray_cells(points, sensor)
    return points[~np.isin(rows, dropped)]


def swapped_columns(
    points: np.ndarray, level: float, rng: np.random.Generator, sensor: Sensor | str = "hdl64"
) -> np.ndarray:
    """round(level * W / 2) random pairs of azimuth columns trade places: each point rotated about z by the
    difference of the two columns' centre azimuths."""
    points, sensor = _check(points, level, "swapped_columns"), get_sensor(sensor)
    order = rng.permutation(sensor.width)  # pairs (order[0], order[1]), (order[2], order[3]), ...
    num_pairs = round(level * sensor.width / 2)
    if num_pairs == 0 or len(points) == 0:
        return points
    target = np.arange(sensor.width)  # (W,) the column each column's points go to
    first, second = order[0 : 2 * num_pairs : 2], order[1 : 2 * num_pairs : 2]
    target[first], target[second] = second, first
    _, azimuth = ray_angles(sensor, sensor.num_rings, sensor.width, "beam")
    azimuth = azimuth.double().numpy()  # (W,) centre azimuth of each column, radians
    _, cols = ray_cells(points, sensor)
    moved = (cols >= 0) & (target[cols] != cols)
    angle = azimuth[target[cols[moved]]] - azimuth[cols[moved]]  # (M,)
    x, y = points[moved, 0].astype(np.float64), points[moved, 1].astype(np.float64)
    out = points.copy()
    out[moved, 0] = (x * np.cos(angle) - y * np.sin(angle)).astype(np.float32)
    out[moved, 1] = (x * np.sin(angle) + y * np.cos(angle)).astype(np.float32)
    return out


def corrupt(
    points: np.ndarray, kind: str, level: float, rng: np.random.Generator, sensor: Sensor | str = "hdl64"
) -> np.ndarray:
    """One of CORRUPTIONS at `level` in [0, 1] of a scan (N, 4); an InputError naming the accepted kinds otherwise."""
    if kind == "depth_noise":
        return depth_noise(points, level, rng)
    elif kind == "smeared_walls":
        return smeared_walls(points, level, rng, sensor)
    elif kind == "dropped_rows":
        return dropped_rows(points, level, rng, sensor)
    elif kind == "swapped_columns":
        return swapped_columns(points, level, rng, sensor)
    raise InputError(f"corruption {kind!r} is not one of {', '.join(CORRUPTIONS)}")
