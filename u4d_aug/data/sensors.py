"""LiDAR sensors: ring elevation tables, range limits, default range-image sizes, intensity response (HDL-64E,
HDL-32E, yaml)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from u4d_aug.errors import InputError
from u4d_aug.presets import resolve_config_path

__all__ = [
    "SENSOR_NAMES",
    "Sensor",
    "fit_intensity_response",
    "get_sensor",
    "hdl32",
    "hdl64",
    "intensity_response",
    "load_sensor_yaml",
    "measure_ring_elevations",
]

SENSOR_NAMES = ("hdl64", "hdl32")


@dataclass(frozen=True)
class Sensor:
    """A spinning LiDAR: ring elevations (top ring first), valid range and default range-image size."""

    name: str
    elevations_deg: tuple[float, ...]  # (num_rings,) degrees, strictly decreasing: top ring = row 0
    min_range: float  # metres; returns closer than this are dropped
    max_range: float  # metres; returns farther than this are dropped; also d_max of the depth encoding
    height: int  # default range-image rows
    width: int  # default range-image columns (azimuth bins)
    fov_up_deg: float  # upper edge of the "linear" row mode (R2DM spherical projection)
    fov_down_deg: float  # lower edge of the "linear" row mode
    # intensity response (`intensity_response`, applied by the simulator): a return of remission r in [0, 1] on the
    # scale the simulated world is tuned to (KITTI HDL-64E remission) reports clip(floor + gain * r ** gamma, 0, 1);
    # the defaults (0, 1, 1) report r unchanged
    intensity_floor: float = 0.0
    intensity_gain: float = 1.0
    intensity_gamma: float = 1.0

    def __post_init__(self) -> None:
        where = f"sensor {self.name!r}"
        if len(self.elevations_deg) < 1:
            raise InputError(f"{where}: elevations_deg must list at least one ring elevation")
        elevations = np.asarray(self.elevations_deg, dtype=np.float64)
        if not np.all(np.isfinite(elevations)) or np.any(np.abs(elevations) >= 90.0):
            raise InputError(f"{where}: elevations_deg must be finite degrees in (-90, 90)")
        if np.any(np.diff(elevations) >= 0):
            raise InputError(f"{where}: elevations_deg must be strictly decreasing (top ring first)")
        if not 0.0 < self.min_range < self.max_range or not math.isfinite(self.max_range):
            raise InputError(
                f"{where}: expected 0 < min_range < max_range < inf, got {self.min_range}, {self.max_range}"
            )
        if self.height < 1 or self.width < 1:
            raise InputError(f"{where}: height and width must be positive, got {self.height}x{self.width}")
        if not -90.0 <= self.fov_down_deg < self.fov_up_deg <= 90.0:
            raise InputError(f"{where}: expected -90 <= fov_down_deg < fov_up_deg <= 90")
        if not 0.0 <= self.intensity_floor < 1.0:
            raise InputError(f"{where}: expected 0 <= intensity_floor < 1, got {self.intensity_floor}")
        for key in ("intensity_gain", "intensity_gamma"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0.0):
                raise InputError(f"{where}: {key} must be a finite number > 0, got {value}")

    @property
    def num_rings(self) -> int:
        return len(self.elevations_deg)

    @property
    def reports_remission(self) -> bool:
        """True when the intensity response is the identity: the sensor reports the simulated remission as it is."""
        return (self.intensity_floor, self.intensity_gain, self.intensity_gamma) == (0.0, 1.0, 1.0)


def intensity_response(sensor: Sensor, remission: np.ndarray) -> np.ndarray:
    """Intensity the sensor reports for remission in [0, 1]: clip(floor + gain * r ** gamma, 0, 1), monotone."""
    r = np.clip(np.asarray(remission), 0.0, 1.0)
    out = sensor.intensity_floor + sensor.intensity_gain * np.power(r, sensor.intensity_gamma)
    return np.clip(out, 0.0, 1.0).astype(r.dtype, copy=False)


RESPONSE_LEVELS = np.linspace(0.01, 0.99, 99)  # quantile levels matched by fit_intensity_response


def fit_intensity_response(
    remission: np.ndarray, target: np.ndarray, levels: np.ndarray = RESPONSE_LEVELS
) -> tuple[float, float, float]:
    """(floor, gain, gamma) by quantile matching: least squares of log f(Q_remission(p)) - log Q_target(p) over the
    quantile levels p, both sides floored at 1/255 (one count of an 8-bit intensity); the log weighs low and high
    intensities alike, as real ones span two decades."""
    from scipy.optimize import least_squares

    source = np.quantile(np.asarray(remission, dtype=np.float64), levels)
    wanted = np.log(np.maximum(np.quantile(np.asarray(target, dtype=np.float64), levels), 1.0 / 255.0))

    def residual(theta: np.ndarray) -> np.ndarray:
        floor, gain, gamma = theta
        return np.log(np.clip(floor + gain * source**gamma, 1.0 / 255.0, 1.0)) - wanted

    fit = least_squares(residual, x0=[0.01, 1.0, 2.0], bounds=([0.0, 0.01, 0.1], [0.5, 10.0, 10.0]))
    floor, gain, gamma = (float(v) for v in fit.x)
    return floor, gain, gamma


def measure_ring_elevations(points: np.ndarray, debounce: int = 500) -> np.ndarray:
    """Median elevation (degrees) of each ring of a scan stored ring by ring, as in KITTI velodyne files.

    A new ring starts where the azimuth, taken relative to the first point, wraps around (drops by more
    than pi); a wrap within `debounce` points of the last ring start is ignored (jitter at the seam).
    Returns (num_rings,) in storage order (top ring first for KITTI).
    """
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    if len(xyz) == 0:
        raise InputError("measure_ring_elevations: empty scan")
    azimuth = np.mod(np.arctan2(xyz[:, 1], xyz[:, 0]) - np.arctan2(xyz[0, 1], xyz[0, 0]), 2.0 * np.pi)
    wraps = np.flatnonzero(np.diff(azimuth) < -np.pi) + 1
    starts = [0]
    for index in wraps:  # loop over <= a few hundred wrap candidates, not over points
        if index - starts[-1] >= debounce:
            starts.append(int(index))
    bounds = np.append(starts, len(xyz))
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    return np.array([np.median(elevation[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)])


# HDL-64E ring elevations (degrees, top ring first) MEASURED from the real KITTI scans in
# ../shared/data/real/semantickitti/sequences/00/velodyne/00000{0..5}.bin: `measure_ring_elevations` on each
# scan (64 rings in every scan), then the median over the 6 scans per ring, rounded to 2 decimals.
# Upper block ~0.335 deg apart, lower block ~0.495 deg apart, 0.63 deg gap between the blocks.
_HDL64_ELEVATIONS_DEG = (
    2.61, 2.23, 2.00, 1.54, 1.26, 0.83, 0.57, 0.18,
    -0.16, -0.57, -0.88, -1.22, -1.57, -1.87, -2.17, -2.52,
    -2.84, -3.24, -3.52, -3.91, -4.22, -4.58, -4.89, -5.18,
    -5.54, -5.85, -6.15, -6.41, -6.78, -7.14, -7.38, -7.77,
    -8.40, -8.91, -9.37, -9.76, -10.22, -10.82, -11.32, -11.75,
    -12.20, -12.62, -13.15, -13.67, -14.24, -14.68, -15.17, -15.55,
    -16.17, -16.69, -17.26, -17.72, -18.21, -18.63, -19.07, -19.63,
    -20.13, -20.79, -21.26, -21.68, -22.11, -22.75, -23.21, -23.74,
)  # fmt: skip


def hdl64() -> Sensor:
    """Velodyne HDL-64E (KITTI): measured ring table, R2DM range 1.45-80 m, 64x1024, linear FOV +3/-25 deg."""
    return Sensor(
        name="hdl64",
        elevations_deg=_HDL64_ELEVATIONS_DEG,
        min_range=1.45,
        max_range=80.0,
        height=64,
        width=1024,
        fov_up_deg=3.0,
        fov_down_deg=-25.0,
    )


def hdl32() -> Sensor:
    """Velodyne HDL-32E (nuScenes): 32 rings evenly +10.67..-30.67 deg, 1-100 m, 32x1024, FOV +10/-30 deg.

    Ring table from the HDL-32E datasheet; the ring medians of the nuScenes demo scan agree within 0.12 deg
    (SOURCES.md: -30.61..+10.66). 1 m = the devkit's remove_close(1.0); 100 m drops 0.04% of that scan
    (max 102.9 m). 32x1024 and +10/-30 deg are the LiDARGen/LiDM nuScenes settings.

    Intensity response: nuScenes' LIDAR_TOP reports 0-255 counts (read as / 255) that sit far lower than KITTI's
    remission (half the returns below 0.05), so a simulated return of remission r reports
    clip(0.009 + 1.08 * r ** 2.68, 0, 1): weak returns the simulator reads as 0 report ~2 counts, r = 0.28 (the
    simulated median) reports 0.045, r >= 0.97 saturates. Fitted by `benchmarks/diagnostics/fit_sensor_response.py`
    (quantile matching, `fit_intensity_response`) of the nuScenes-like world (configs/sim/nuscenes.yaml, seeds 7-9) to
    the one real keyframe available (../shared/data/real/nuscenes_mmdet3d_demo, Singapore, 26.7k returns): a sensor
    property, but measured on one place, so it also absorbs that place's surfaces against the simulated ones, and
    the few returns above r = 0.6 leave gain and gamma loosely set (the curve below r = 0.4 is firm).
    """
    elevations = np.linspace(10.67, -30.67, 32)
    return Sensor(
        name="hdl32",
        elevations_deg=tuple(round(float(e), 4) for e in elevations),
        min_range=1.0,
        max_range=100.0,
        height=32,
        width=1024,
        fov_up_deg=10.0,
        fov_down_deg=-30.0,
        intensity_floor=0.009,  # what a return too weak for the simulator (remission 0) reports: ~2 of 255
        intensity_gain=1.08,
        intensity_gamma=2.68,  # > 1: low and middle remission are pressed towards 0, bright returns kept
    )


_FIELD_TYPES: dict[str, str] = {
    "name": "str",
    "elevations_deg": "list of numbers",
    "min_range": "number",
    "max_range": "number",
    "height": "int",
    "width": "int",
    "fov_up_deg": "number",
    "fov_down_deg": "number",
    "intensity_floor": "number",
    "intensity_gain": "number",
    "intensity_gamma": "number",
}
_REQUIRED = ("elevations_deg", "min_range", "max_range")


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_type(path: Path, key: str, value: Any) -> Any:
    """Return the value converted to its field type, or raise InputError naming the key."""
    expected = _FIELD_TYPES[key]
    ok = {
        "str": isinstance(value, str),
        "int": isinstance(value, int) and not isinstance(value, bool),
        "number": _is_number(value),
        "list of numbers": isinstance(value, list) and all(_is_number(v) for v in value),
    }[expected]
    if not ok:
        raise InputError(f"{path}: key '{key}' expects {expected}, got {value!r}")
    if expected == "number":
        return float(value)
    if expected == "list of numbers":
        return tuple(float(v) for v in value)
    return value


def load_sensor_yaml(path: str | Path) -> Sensor:
    """Sensor from a yaml file with the fields of `Sensor`; height defaults to the ring count, width to 1024,
    the linear FOV to the ring table widened by half a ring spacing at each end (presets: `sensors/NAME.yaml`)."""
    path = resolve_config_path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise InputError(f"{path}: cannot read sensor file ({error.strerror})") from error
    except yaml.YAMLError as error:
        raise InputError(f"{path}: not valid yaml ({str(error).splitlines()[0]})") from error
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of sensor fields ({', '.join(_FIELD_TYPES)})")
    valid = [field.name for field in dataclasses.fields(Sensor)]
    unknown = sorted(str(key) for key in data if key not in valid)
    if unknown:
        raise InputError(f"{path}: unknown key(s) {', '.join(unknown)}; valid keys: {', '.join(valid)}")
    missing = [key for key in _REQUIRED if key not in data]
    if missing:
        raise InputError(f"{path}: missing required key(s) {', '.join(missing)}")
    values = {key: _check_type(path, key, value) for key, value in data.items()}
    elevations = values["elevations_deg"] or (0.0,)  # an empty table is rejected by Sensor below
    half_spacing = (elevations[0] - elevations[-1]) / (2 * (len(elevations) - 1)) if len(elevations) > 1 else 0.5
    values.setdefault("name", path.stem)
    values.setdefault("height", len(values["elevations_deg"]))
    values.setdefault("width", 1024)
    values.setdefault("fov_up_deg", round(elevations[0] + abs(half_spacing), 4))
    values.setdefault("fov_down_deg", round(elevations[-1] - abs(half_spacing), 4))
    try:
        return Sensor(**values)
    except InputError as error:
        raise InputError(f"{path}: {error}") from error


def get_sensor(name_or_yaml: str | Path | Sensor) -> Sensor:
    """'hdl64', 'hdl32' or the path of a sensor yaml file (see configs/sensors/example_sensor.yaml)."""
    if isinstance(name_or_yaml, Sensor):
        return name_or_yaml
    text = str(name_or_yaml)
    if text == "hdl64":
        return hdl64()
    if text == "hdl32":
        return hdl32()
    path = Path(text)
    if path.suffix.lower() in (".yaml", ".yml") or path.is_file():
        return load_sensor_yaml(path)
    raise InputError(f"unknown sensor {text!r}; expected one of {', '.join(SENSOR_NAMES)} or a sensor .yaml file")
