"""SemanticKITTI and nuScenes file formats: readers and their exact-inverse atomic writers.

Source: ../shared/reference/segmentation_protocols.md §5 (LaserMix b72cbd3 `laserscan.py`; PRBonn
semantic-kitti-api `generate_sequential.py`; nuScenes devkit `LidarPointCloud`). Every reader checks sizes and
raises `InputError` naming the file; writers go through `u4d_aug.io.atomic_open`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from u4d_aug.errors import InputError
from u4d_aug.io import atomic_open, atomic_write_text
from u4d_aug.memory import check_fits, gib

__all__ = [
    "KittiFrame",
    "NuscenesScan",
    "label_path_for",
    "load_kitti_frame",
    "read_kitti_scan",
    "write_kitti_scan",
    "read_kitti_label",
    "write_kitti_label",
    "read_calib",
    "write_calib",
    "read_poses",
    "write_poses",
    "read_times",
    "write_times",
    "read_nuscenes_scan",
    "write_nuscenes_scan",
    "read_nuscenes_lidarseg",
    "write_nuscenes_lidarseg",
]

PathLike = str | os.PathLike
KITTI_COLUMNS = 4  # x, y, z, remission
NUSCENES_COLUMNS = 5  # x, y, z, intensity (0..255), ring


@dataclass
class KittiFrame:
    """One SemanticKITTI scan with its raw labels (None when no label file was given)."""

    points: np.ndarray  # (N, 4) float32 x, y, z [m, LiDAR frame], remission [0, 1]
    semantic: np.ndarray | None  # (N,) uint16 raw semantic ids (map with labels.map_semantickitti)
    instance: np.ndarray | None  # (N,) uint16 instance ids


@dataclass
class NuscenesScan:
    """One nuScenes LIDAR_TOP sweep without ego returns; `keep` filters per-point files the same way."""

    points: np.ndarray  # (N, 4) float32 x, y, z [m], intensity / 255 in [0, 1]
    ring: np.ndarray  # (N,) int64 laser index (0 = bottom ring on the HDL-32E)
    keep: np.ndarray  # (N_raw,) bool: which rows of the file survive (finite and beyond remove_close)


# ------------------------------------------------------------------------------------------------------------
# helpers


def _read_records(path: PathLike, dtype: str, columns: int, what: str) -> np.ndarray:
    """Read a flat binary file as (N, columns) records; it must exist and its size divide evenly."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a {what} file")
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    record = np.dtype(dtype).itemsize * columns
    size = path.stat().st_size
    check_fits(size, f"{path} ({what}, {gib(size)})", "no LiDAR scan is this large: is it the right file?")
    if size % record:
        raise InputError(
            f"{path}: size {size} bytes is not a multiple of {record} ({what}: {columns} x {np.dtype(dtype).name})"
        )
    data = np.fromfile(path, dtype=dtype)
    return data.reshape(-1, columns) if columns > 1 else data


def usable_rows(points: np.ndarray) -> np.ndarray:
    """(N,) bool: rows whose values are all finite and whose x, y, z lie within MAX_COORDINATE m (a sensor's
    plausible range; beyond it voxel grids overflow and nets return NaN)."""
    finite = np.isfinite(points).all(axis=1)
    with np.errstate(invalid="ignore"):
        return finite & (np.abs(points[:, :3]) <= MAX_COORDINATE).all(axis=1)


def _drop_unusable(path: PathLike, points: np.ndarray) -> np.ndarray:
    """Boolean mask of `usable_rows`; warns with the counts when some rows hold NaN/inf or lie beyond 10 km."""
    usable = usable_rows(points)
    dropped = int(len(points) - usable.sum())
    if dropped:
        nonfinite = int(len(points) - np.isfinite(points).all(axis=1).sum())
        far = dropped - nonfinite
        reasons = [f"{nonfinite} with NaN/inf values"] * bool(nonfinite) + [
            f"{far} beyond {MAX_COORDINATE:g} m"
        ] * bool(far)
        warnings.warn(f"{path}: dropped {dropped} of {len(points)} points ({', '.join(reasons)})", stacklevel=3)
    return usable


def _format_floats(values: np.ndarray) -> str:
    """Shortest text that reads back to the same float64 (repr), space-separated."""
    return " ".join(repr(float(v)) for v in np.asarray(values, dtype=np.float64).ravel())


def _parse_floats(path: Path, lineno: int, fields: list[str], count: int, what: str) -> np.ndarray:
    if len(fields) != count:
        raise InputError(f"{path}:{lineno}: expected {count} numbers ({what}), got {len(fields)}")
    try:
        return np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}:{lineno}: expected {count} numbers ({what}), got non-numeric text") from None


def _text_lines(path: PathLike, what: str) -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of the non-blank lines of a text file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    with open(path, encoding="utf-8") as f:
        return [(i, line.strip()) for i, line in enumerate(f, start=1) if line.strip()]


def _homogeneous(matrix_3x4: np.ndarray) -> np.ndarray:
    out = np.eye(4, dtype=np.float64)
    out[:3, :4] = matrix_3x4
    return out


# ------------------------------------------------------------------------------------------------------------
# SemanticKITTI scans and labels


def label_path_for(scan_path: PathLike) -> Path:
    """`.../velodyne/X.bin` -> `.../labels/X.label` (SemanticKITTI); elsewhere `X.label` beside the scan."""
    scan_path = Path(scan_path)
    stem = scan_path.name[: -len(".bin")] if scan_path.name.endswith(".bin") else scan_path.stem
    if scan_path.parent.name == "velodyne":
        return scan_path.parent.parent / "labels" / f"{stem}.label"
    return scan_path.parent / f"{stem}.label"


def read_kitti_scan(path: PathLike) -> np.ndarray:
    """Read a KITTI velodyne `.bin` -> (N, 4) float32 x, y, z, remission (rows as stored, NaN kept).

    Checked against what a KITTI scan holds (`check_kitti_scan`): a nuScenes file named `.bin` is an error,
    float64 values or an intensity outside [0, 1] a warning.
    """
    points = _read_records(path, "<f4", KITTI_COLUMNS, "KITTI scan")
    if len(points) == 0:
        raise InputError(f"{path}: empty scan (0 points)")
    check_kitti_scan(path, points)
    return points


def check_kitti_scan(path: PathLike, points: np.ndarray) -> None:
    """Sanity of (N, 4) float32 records read from a KITTI `.bin`: coordinates within 10 km, intensity in [0, 1].

    Where they are not, the file is looked at again: 5 float32 columns with an integral ring in the last (a nuScenes
    `.pcd.bin` renamed) raise an InputError; values that are plausible read as float64 warn, as does an intensity
    in [0, 255] (another scale) or beyond.
    """
    finite = np.isfinite(points).all(axis=1)
    kept = points[finite]
    coordinates_ok = bool((np.abs(kept[:, :3]) <= MAX_COORDINATE).all())
    intensity = kept[:, 3]
    intensity_ok = bool(((intensity >= 0.0) & (intensity <= 1.0)).all())
    if coordinates_ok and intensity_ok:
        return  # the common case: one pass over the points
    if _looks_like_nuscenes(points):
        raise InputError(
            f"{path}: holds 5 float32 columns (x, y, z, intensity 0-255, ring) like a nuScenes scan, not KITTI's "
            "4; name it *.pcd.bin to read it as nuScenes"
        )
    if len(points) % 2 == 0 and _implausible_share(points) > 0.1 and _implausible_share(points.view("<f8")) < 0.01:
        _warn_scan(
            "float64",
            f"{path}: its values look like float64 (x, y, z, intensity), read here as KITTI's float32; convert it "
            "with points.astype(np.float32).tofile(...)",
        )
    elif not intensity_ok and len(intensity):
        low, high = float(intensity.min()), float(intensity.max())
        if low >= 0.0 and high <= 255.0:
            _warn_scan(
                "intensity",
                f"{path}: intensity up to {high:g}, on a 0-255 scale it seems; KITTI remission is in [0, 1] "
                "(divide by 255)",
            )
        else:
            _warn_scan(
                "intensity",
                f"{path}: intensity in [{low:g}, {high:g}], outside [0, 1] and [0, 255]; is this a KITTI scan?",
            )


MAX_COORDINATE = 1e4  # m: no LiDAR return is 10 km away
_SCAN_WARNINGS: dict[str, int] = {}  # warnings given per kind of problem (a dataset would repeat one per file)
_SCAN_WARNING_LIMIT = 3


def _warn_scan(kind: str, message: str) -> None:
    """Warn about a scan file, at most _SCAN_WARNING_LIMIT times per kind of problem in this process."""
    count = _SCAN_WARNINGS.get(kind, 0)
    _SCAN_WARNINGS[kind] = count + 1
    if count < _SCAN_WARNING_LIMIT:
        more = " (further files with this problem are not reported)" if count + 1 == _SCAN_WARNING_LIMIT else ""
        warnings.warn(message + more, stacklevel=4)


def _looks_like_nuscenes(points: np.ndarray) -> bool:
    """Whether the float32 values read as 5 columns end each row with a ring number (integral, 0-255)."""
    values = points.reshape(-1)
    if values.size % NUSCENES_COLUMNS or values.size < 2 * NUSCENES_COLUMNS:
        return False
    rows = values.reshape(-1, NUSCENES_COLUMNS)
    ring, intensity = rows[:, 4], rows[:, 3]
    with np.errstate(invalid="ignore"):
        ring_ok = np.isfinite(ring).all() and (ring == np.round(ring)).all() and ring.min() >= 0 and ring.max() < 256
        return bool(ring_ok and np.isfinite(intensity).all() and intensity.min() >= 0 and intensity.max() <= 255)


def _implausible_share(values: np.ndarray) -> float:
    """Share of values no scan holds: NaN/inf, beyond 10 km, or tiny but not 0 (the bit patterns of another dtype)."""
    with np.errstate(invalid="ignore", over="ignore"):  # the bit patterns of another dtype may be signalling NaNs
        magnitude = np.abs(values.astype(np.float64, copy=False).reshape(-1))
        bad = ~np.isfinite(magnitude) | (magnitude > MAX_COORDINATE) | ((magnitude > 0) & (magnitude < 1e-20))
    return float(bad.mean()) if bad.size else 0.0


def write_kitti_scan(path: PathLike, points: np.ndarray) -> None:
    """Write (N, 4) points as a KITTI velodyne `.bin` (float32, row-major), atomically."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != KITTI_COLUMNS or len(points) == 0:
        raise InputError(f"{path}: expected (N>0, 4) points x, y, z, remission, got shape {points.shape}")
    with atomic_open(path, "wb") as f:
        f.write(np.ascontiguousarray(points, dtype="<f4").tobytes())


def read_kitti_label(path: PathLike, num_points: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a SemanticKITTI `.label` (uint32) -> (semantic = low 16 bits, instance = high 16), both uint16."""
    label = _read_records(path, "<u4", 1, "SemanticKITTI label")
    if num_points is not None and len(label) != num_points:
        raise InputError(f"{path}: {len(label)} labels but the scan has {num_points} points")
    return (label & 0xFFFF).astype(np.uint16), (label >> 16).astype(np.uint16)


def write_kitti_label(path: PathLike, semantic: np.ndarray, instance: np.ndarray | None = None) -> None:
    """Write raw semantic ids (and instance ids, default 0) as a SemanticKITTI `.label`, atomically."""
    semantic = np.asarray(semantic)
    instance = np.zeros_like(semantic) if instance is None else np.asarray(instance)
    if semantic.ndim != 1 or instance.shape != semantic.shape:
        raise InputError(
            f"{path}: expected 1-D semantic and instance of equal length, got {semantic.shape}, {instance.shape}"
        )
    for name, values in (("semantic", semantic), ("instance", instance)):
        if values.size and (values.min() < 0 or values.max() > 0xFFFF):
            raise InputError(f"{path}: {name} ids must fit in 16 bits (0..65535)")
    label = (instance.astype(np.uint32) << 16) | semantic.astype(np.uint32)
    with atomic_open(path, "wb") as f:
        f.write(label.astype("<u4").tobytes())


def load_kitti_frame(scan_path: PathLike, label_path: PathLike | None = None) -> KittiFrame:
    """Scan (+ labels, one per point); NaN/inf rows and rows beyond 10 km are dropped with their labels, with a
    warning."""
    raw = read_kitti_scan(scan_path)
    semantic = instance = None
    if label_path is not None:
        semantic, instance = read_kitti_label(label_path, num_points=len(raw))
    finite = _drop_unusable(scan_path, raw)
    if not finite.all():
        if not finite.any():
            raise InputError(f"{scan_path}: empty scan (all {len(raw)} points are NaN/inf or beyond 10 km)")
        raw = raw[finite]
        if semantic is not None and instance is not None:  # read together
            semantic, instance = semantic[finite], instance[finite]
    return KittiFrame(points=raw, semantic=semantic, instance=instance)


# ------------------------------------------------------------------------------------------------------------
# SemanticKITTI calib, poses, times


def read_calib(path: PathLike) -> dict[str, np.ndarray]:
    """Read KITTI-odometry `calib.txt` (`P0:`..`P3:`, `Tr:`; 12 floats each) -> {key: (3, 4) float64}."""
    calib: dict[str, np.ndarray] = {}
    for lineno, line in _text_lines(path, "calib"):
        key, sep, rest = line.partition(":")
        if not sep or not key.strip() or " " in key.strip():
            raise InputError(f"{path}:{lineno}: expected 'KEY: 12 numbers' (e.g. 'Tr: ...'), got {line[:40]!r}")
        calib[key.strip()] = _parse_floats(Path(path), lineno, rest.split(), 12, f"3x4 matrix {key.strip()}").reshape(
            3, 4
        )
    if not calib:
        raise InputError(f"{path}: calib file holds no 'KEY: 12 numbers' lines")
    return calib


def write_calib(path: PathLike, calib: Mapping[str, np.ndarray]) -> None:
    """Write {key: (3, 4)} as `calib.txt`, keys in the given order, atomically."""
    lines = []
    for key, matrix in calib.items():
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (3, 4):
            raise InputError(f"{path}: calib entry {key!r} must be (3, 4), got {matrix.shape}")
        lines.append(f"{key}: {_format_floats(matrix)}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def _velo_to_cam(calib: Mapping[str, np.ndarray] | PathLike, where: PathLike) -> np.ndarray:
    """4x4 Tr (velodyne -> cam0) from a calib dict or a calib.txt path."""
    if not isinstance(calib, Mapping):
        calib = read_calib(calib)
    if "Tr" not in calib:
        raise InputError(f"{where}: calib has no 'Tr' entry (velodyne -> cam0); keys: {sorted(calib)}")
    return _homogeneous(np.asarray(calib["Tr"], dtype=np.float64).reshape(3, 4))


def read_poses(path: PathLike, calib: Mapping[str, np.ndarray] | PathLike | None = None) -> np.ndarray:
    """Read `poses.txt` -> (T, 4, 4) float64: LiDAR poses T = Tr^-1 P Tr with calib, cam0 poses P without."""
    rows = [_parse_floats(Path(path), i, line.split(), 12, "3x4 pose") for i, line in _text_lines(path, "poses")]
    if not rows:
        raise InputError(f"{path}: poses file is empty")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))  # (T, 4, 4)
    poses[:, :3, :4] = np.stack(rows).reshape(-1, 3, 4)
    if calib is None:
        return poses
    tr = _velo_to_cam(calib, path)
    return np.linalg.inv(tr) @ poses @ tr


def write_poses(
    path: PathLike, lidar_poses: np.ndarray, calib: Mapping[str, np.ndarray] | PathLike | None = None
) -> None:
    """Write (T, 4, 4) LiDAR poses as cam0-frame `poses.txt` lines P = Tr T Tr^-1 (as is without calib)."""
    poses = np.asarray(lidar_poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise InputError(f"{path}: expected (T>0, 4, 4) poses, got shape {poses.shape}")
    if not np.allclose(poses[:, 3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{path}: poses must be homogeneous (last row 0 0 0 1)")
    if calib is not None:
        tr = _velo_to_cam(calib, path)
        poses = tr @ poses @ np.linalg.inv(tr)
    atomic_write_text(path, "".join(_format_floats(p[:3, :4]) + "\n" for p in poses))


def read_times(path: PathLike) -> np.ndarray:
    """Read `times.txt` (one time in seconds per line) -> (T,) float64."""
    times = [
        _parse_floats(Path(path), i, line.split(), 1, "time in seconds")[0] for i, line in _text_lines(path, "times")
    ]
    if not times:
        raise InputError(f"{path}: times file is empty")
    return np.array(times, dtype=np.float64)


def write_times(path: PathLike, times: np.ndarray) -> None:
    """Write (T,) seconds as `times.txt`, atomically."""
    times = np.asarray(times, dtype=np.float64)
    if times.ndim != 1 or len(times) == 0:
        raise InputError(f"{path}: expected (T>0,) times, got shape {times.shape}")
    atomic_write_text(path, "".join(repr(float(t)) + "\n" for t in times))


# ------------------------------------------------------------------------------------------------------------
# nuScenes


def read_nuscenes_scan(path: PathLike, remove_close: float = 1.0) -> NuscenesScan:
    """Read a nuScenes `.pcd.bin` (float32 x5); drop NaN/inf rows (warning) and returns within remove_close m.

    Unlike the devkit's `remove_close` (an |x|, |y| < r box), the radius here is the 3D range, the definition
    behind the 8,029 ego returns counted in ../shared/data/real/SOURCES.md; 0 disables it.
    """
    if remove_close < 0:
        raise InputError(f"{path}: remove_close must be >= 0 metres, got {remove_close}")
    raw = _read_records(path, "<f4", NUSCENES_COLUMNS, "nuScenes scan")
    if len(raw) == 0:
        raise InputError(f"{path}: empty scan (0 points)")
    keep = _drop_unusable(path, raw)
    if remove_close > 0:
        keep &= np.linalg.norm(raw[:, :3].astype(np.float64), axis=1) >= remove_close
    if not keep.any():
        raise InputError(f"{path}: empty scan (no finite point beyond remove_close={remove_close} m)")
    kept = raw[keep]
    points = kept[:, :4].copy()
    points[:, 3] /= 255.0
    return NuscenesScan(points=points, ring=kept[:, 4].astype(np.int64), keep=keep)


def write_nuscenes_scan(path: PathLike, points: np.ndarray, ring: np.ndarray) -> None:
    """Write (N, 4) points (intensity in [0, 1]) and (N,) rings as a nuScenes `.pcd.bin` (intensity x 255)."""
    points = np.asarray(points, dtype=np.float32)
    ring = np.asarray(ring)
    if points.ndim != 2 or points.shape[1] != 4 or len(points) == 0 or ring.shape != (len(points),):
        raise InputError(f"{path}: expected (N>0, 4) points and (N,) ring, got {points.shape}, {ring.shape}")
    records = np.empty((len(points), NUSCENES_COLUMNS), dtype=np.float32)
    records[:, :3] = points[:, :3]
    records[:, 3] = points[:, 3] * np.float32(255.0)
    records[:, 4] = ring
    with atomic_open(path, "wb") as f:
        f.write(records.tobytes())


def read_nuscenes_lidarseg(path: PathLike, num_points: int | None = None) -> np.ndarray:
    """Read a nuScenes `_lidarseg.bin` -> (N_raw,) uint8 raw ids; filter with `NuscenesScan.keep`."""
    labels = _read_records(path, "u1", 1, "nuScenes lidarseg")
    if num_points is not None and len(labels) != num_points:
        raise InputError(f"{path}: {len(labels)} labels but the scan has {num_points} points")
    return labels


def write_nuscenes_lidarseg(path: PathLike, labels: np.ndarray) -> None:
    """Write (N,) raw lidarseg ids (0..255) as uint8, atomically."""
    labels = np.asarray(labels)
    if labels.ndim != 1 or (labels.size and (labels.min() < 0 or labels.max() > 255)):
        raise InputError(f"{path}: expected 1-D lidarseg ids in 0..255")
    with atomic_open(path, "wb") as f:
        f.write(labels.astype(np.uint8).tobytes())
