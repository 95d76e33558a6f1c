"""nuScenes v1.0 json tables: the LIDAR_TOP frames of each scene with their poses and lidarseg files, and back.

Source: ../shared/reference/segmentation_protocols.md §5 (labels `lidarseg/<version>/<token>_lidarseg.bin` resolved
through lidarseg.json; calibrated_sensor = lidar -> ego, ego_pose = ego -> global, quaternions w, x, y, z) and the
nuScenes devkit schema (scene, sample, sample_data, ego_pose, calibrated_sensor, sensor, lidarseg, category). Only
the tables the LiDAR needs are read; a missing table, field or reference is one InputError naming the file, the
record and the field. `write_nuscenes_tables` is the inverse (tokens derived from the frames' own tokens).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from u4d_aug.data.labels import NUSCENES_RAW_NAMES
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_write_text

__all__ = [
    "LIDAR_CHANNEL",
    "NUSCENES_VERSION",
    "LidarFrame",
    "NuscenesIndex",
    "derive_token",
    "lidarseg_filename",
    "matrix_to_quaternion",
    "pose_matrix",
    "pose_parts",
    "quaternion_to_matrix",
    "read_nuscenes_index",
    "scan_filename",
    "write_nuscenes_tables",
]

PathLike = str | os.PathLike
NUSCENES_VERSION = "v1.0-trainval"
LIDAR_CHANNEL = "LIDAR_TOP"
_REQUIRED_TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")


@dataclass(eq=False)
class LidarFrame:
    """One LIDAR_TOP sample_data record: its scan file, time, poses and lidarseg file (None: unlabelled)."""

    token: str  # sample_data token
    timestamp: int  # microseconds
    is_key_frame: bool  # a sample (2 Hz, the frames lidarseg labels) rather than a sweep (20 Hz)
    filename: str  # scan file relative to the root: samples/LIDAR_TOP/*.pcd.bin or sweeps/LIDAR_TOP/*.pcd.bin
    ego_to_world: np.ndarray  # (4, 4) float64 ego_pose: ego -> global
    lidar_to_ego: np.ndarray  # (4, 4) float64 calibrated_sensor: lidar -> ego
    lidarseg: str | None = None  # lidarseg/<version>/<token>_lidarseg.bin relative to the root

    @property
    def lidar_to_world(self) -> np.ndarray:
        """(4, 4) lidar -> global: ego_pose @ calibrated_sensor (the mmdet3d lidar2global)."""
        return self.ego_to_world @ self.lidar_to_ego


@dataclass(eq=False)
class NuscenesIndex:
    """The LIDAR_TOP frames of a nuScenes root, by scene name, in timestamp order (shared: do not modify)."""

    root: Path
    version: str
    scenes: dict[str, list[LidarFrame]]

    @property
    def tables(self) -> Path:
        return self.root / self.version


# ------------------------------------------------------------------------------------------------------------
# geometry: quaternions (w, x, y, z) <-> rotation matrices, translation + quaternion <-> 4x4


def quaternion_to_matrix(rotation: Sequence[float]) -> np.ndarray:
    """Unit quaternion (w, x, y, z), normalised here, -> (3, 3) rotation matrix (pyquaternion's convention)."""
    w, x, y, z = np.asarray(rotation, dtype=np.float64) / np.linalg.norm(rotation)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def matrix_to_quaternion(matrix: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> unit quaternion (4,) w, x, y, z with w >= 0 (Shepperd's method)."""
    m = np.asarray(matrix, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q) / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def pose_matrix(translation: Sequence[float], rotation: Sequence[float]) -> np.ndarray:
    """(4, 4) float64 [R(rotation) | translation] of a nuScenes record (translation x, y, z; rotation w, x, y, z)."""
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(rotation)
    pose[:3, 3] = translation
    return pose


def pose_parts(pose: np.ndarray) -> tuple[list[float], list[float]]:
    """Inverse of `pose_matrix`: (translation [x, y, z], rotation [w, x, y, z]) as plain floats for json."""
    pose = np.asarray(pose, dtype=np.float64)
    return [float(v) for v in pose[:3, 3]], [float(v) for v in matrix_to_quaternion(pose[:3, :3])]


# ------------------------------------------------------------------------------------------------------------
# reading


def read_nuscenes_index(root: PathLike, version: str = NUSCENES_VERSION, channel: str = LIDAR_CHANNEL) -> NuscenesIndex:
    """The `channel` frames of every scene under ROOT/VERSION/*.json; cached per process until a table changes."""
    folder = _tables_folder(Path(root), version)
    stamp = tuple(
        (name, path.stat().st_mtime_ns, path.stat().st_size)
        for name in (*_REQUIRED_TABLES, "lidarseg", "category")
        if (path := folder / f"{name}.json").is_file()
    )
    return _read_index(str(Path(root).absolute()), version, channel, stamp)


@functools.lru_cache(maxsize=2)
def _read_index(root: str, version: str, channel: str, stamp: tuple) -> NuscenesIndex:
    """The work of `read_nuscenes_index`; `stamp` (mtime and size of each table) keys the cache."""
    folder = Path(root) / version
    sensors = {r["token"] for r in _read_table(folder, "sensor", ("token", "channel")) if r["channel"] == channel}
    if not sensors:
        raise InputError(f"{folder / 'sensor.json'}: no sensor with channel {channel!r}")
    calibrated = {
        r["token"]: _pose_of(folder / "calibrated_sensor.json", r)
        for r in _read_table(folder, "calibrated_sensor", ("token", "sensor_token", "translation", "rotation"))
        if r["sensor_token"] in sensors
    }
    data_path = folder / "sample_data.json"
    records = [
        r for r in _read_table(folder, "sample_data", ("token", "calibrated_sensor_token"))
        if r["calibrated_sensor_token"] in calibrated
    ]  # fmt: skip
    for record in records:
        _check_fields(data_path, record, ("sample_token", "ego_pose_token", "timestamp", "is_key_frame", "filename"))
    needed = {r["ego_pose_token"] for r in records}
    ego_path, poses = folder / "ego_pose.json", {}
    for record in _read_table(folder, "ego_pose", ("token",)):
        if record["token"] in needed:
            _check_fields(ego_path, record, ("translation", "rotation"))
            poses[record["token"]] = _pose_of(ego_path, record)
    scene_name = {r["token"]: r["name"] for r in _read_table(folder, "scene", ("token", "name"))}
    sample_path = folder / "sample.json"
    scene_of_sample = {
        r["token"]: _reference(sample_path, r, "scene_token", scene_name, "scene.json")
        for r in _read_table(folder, "sample", ("token", "scene_token"))
    }
    lidarseg = _lidarseg_files(folder)
    scenes: dict[str, list[LidarFrame]] = {}
    for record in records:
        token, filename, timestamp = record["token"], record["filename"], record["timestamp"]
        if not isinstance(filename, str) or not filename:
            raise InputError(f"{data_path}: record {token!r} has an empty 'filename' (no scan file)")
        if not isinstance(timestamp, int) or isinstance(timestamp, bool):
            raise InputError(f"{data_path}: record {token!r} field 'timestamp' must be an integer (microseconds)")
        scene = _reference(data_path, record, "sample_token", scene_of_sample, "sample.json")
        scenes.setdefault(scene, []).append(
            LidarFrame(
                token=token,
                timestamp=timestamp,
                is_key_frame=bool(record["is_key_frame"]),
                filename=filename,
                ego_to_world=_reference(data_path, record, "ego_pose_token", poses, "ego_pose.json"),
                lidar_to_ego=calibrated[record["calibrated_sensor_token"]],
                lidarseg=lidarseg.get(token),
            )
        )
    if not scenes:
        raise InputError(f"{data_path}: no sample_data record of channel {channel!r}")
    for frames in scenes.values():
        frames.sort(key=lambda frame: (frame.timestamp, frame.token))
    return NuscenesIndex(root=Path(root), version=version, scenes=dict(sorted(scenes.items())))


def _tables_folder(root: Path, version: str) -> Path:
    """ROOT/VERSION, or an InputError naming the versions ROOT does hold."""
    if not root.is_dir():
        raise InputError(f"{root}: folder not found (expected a nuScenes root with {version}/ and samples/)")
    folder = root / version
    if not folder.is_dir():
        found = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v1.0"))
        hint = f"; it holds {', '.join(found)} (set the version)" if found else " (expected ROOT/v1.0-*/*.json)"
        raise InputError(f"{folder}: nuScenes table folder not found{hint}")
    return folder


def _read_table(folder: Path, name: str, fields: tuple[str, ...]) -> list[dict]:
    """The records of FOLDER/NAME.json, each checked to hold `fields`."""
    path = folder / f"{name}.json"
    if not path.is_file():
        raise InputError(f"{path}: nuScenes table not found (the LiDAR frames need {', '.join(_REQUIRED_TABLES)})")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid json (line {exc.lineno}: {exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the table ({exc})") from None
    if not isinstance(data, list):
        raise InputError(f"{path}: expected a json list of records, got a {type(data).__name__}")
    for record in data:
        _check_fields(path, record, fields)
    return data


def _check_fields(path: Path, record: Any, fields: tuple[str, ...]) -> bool:
    """True when the record is a mapping holding every field; otherwise an InputError naming the first missing."""
    if not isinstance(record, dict):
        raise InputError(f"{path}: expected records as json objects, got a {type(record).__name__}")
    for field in fields:
        if field not in record:
            raise InputError(f"{path}: record {record.get('token', '(no token)')!r} has no {field!r} field")
    return True


def _reference(path: Path, record: dict, field: str, table: Mapping[str, Any], target: str) -> Any:
    """table[record[field]], or an InputError naming the dangling reference."""
    try:
        return table[record[field]]
    except (KeyError, TypeError):
        raise InputError(
            f"{path}: record {record['token']!r} field {field!r} = {record[field]!r} is not a token of {target}"
        ) from None


def _pose_of(path: Path, record: dict) -> np.ndarray:
    """(4, 4) of a record's translation (3 numbers) and rotation (4 numbers, w x y z, non-zero)."""
    translation, rotation = record["translation"], record["rotation"]
    ok = _numbers(translation, 3) and _numbers(rotation, 4) and np.linalg.norm(rotation) > 0
    if not ok:
        raise InputError(
            f"{path}: record {record['token']!r} needs 'translation' [x, y, z] and a non-zero 'rotation' "
            f"[w, x, y, z]; got {translation!r}, {rotation!r}"
        )
    return pose_matrix(translation, rotation)


def _numbers(values: Any, count: int) -> bool:
    return (
        isinstance(values, list)
        and len(values) == count
        and all(isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v) for v in values)
    )


def _lidarseg_files(folder: Path) -> dict[str, str]:
    """sample_data token -> lidarseg file (lidarseg.json; {} when the lidarseg tables are not installed).

    category.json, when present with lidarseg's `index` field, must name the raw ids as the label map does.
    """
    if not (folder / "lidarseg.json").is_file():
        return {}
    path = folder / "category.json"
    if path.is_file():
        for record in _read_table(folder, "category", ("name",)):
            index = record.get("index")
            if index is not None and NUSCENES_RAW_NAMES.get(index) != record["name"]:
                raise InputError(
                    f"{path}: category {record['name']!r} has lidarseg index {index!r}, where the 16-class map "
                    f"expects {NUSCENES_RAW_NAMES.get(index, 'no class')!r}"
                )
    files = {}
    seg_path = folder / "lidarseg.json"
    for record in _read_table(folder, "lidarseg", ("token", "sample_data_token", "filename")):
        if not isinstance(record["filename"], str) or not record["filename"]:
            raise InputError(f"{seg_path}: record {record['token']!r} has an empty 'filename'")
        files[record["sample_data_token"]] = record["filename"]
    return files


# ------------------------------------------------------------------------------------------------------------
# writing


def scan_filename(log: str, timestamp: int, is_key_frame: bool, channel: str = LIDAR_CHANNEL) -> str:
    """samples/LIDAR_TOP/<log>__LIDAR_TOP__<timestamp>.pcd.bin (keyframes) or sweeps/... (the nuScenes naming)."""
    return f"{'samples' if is_key_frame else 'sweeps'}/{channel}/{log}__{channel}__{timestamp}.pcd.bin"


def lidarseg_filename(token: str, version: str = NUSCENES_VERSION) -> str:
    """lidarseg/<version>/<sample_data token>_lidarseg.bin."""
    return f"lidarseg/{version}/{token}_lidarseg.bin"


def derive_token(*parts: object) -> str:
    """32 hex digits derived from the parts (nuScenes tokens are 32 hex digits)."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def write_nuscenes_tables(
    root: PathLike,
    scenes: Mapping[str, Sequence[LidarFrame]],
    version: str = NUSCENES_VERSION,
    channel: str = LIDAR_CHANNEL,
    log: str = "u4d-sim",
) -> None:
    """Write the tables `read_nuscenes_index` reads (+ log.json) for these scenes, atomically, table by table.

    Each scene needs a keyframe; its samples are its keyframes and a sweep belongs to the sample before it (the
    first keyframe for sweeps ahead of it). category.json lists the 32 lidarseg classes with their index.
    """
    folder = Path(root) / version
    sensor_token, log_token = derive_token("sensor", channel), derive_token("log", log)
    tables: dict[str, list[dict]] = {name: [] for name in (*_REQUIRED_TABLES, "lidarseg", "log", "category")}
    tables["sensor"].append({"token": sensor_token, "channel": channel, "modality": "lidar"})
    tables["log"].append({"token": log_token, "logfile": log, "vehicle": "u4d", "date_captured": "", "location": ""})
    tables["category"] = [
        {"token": derive_token("category", index), "name": name, "description": "", "index": index}
        for index, name in sorted(NUSCENES_RAW_NAMES.items())
    ]
    calibrations: dict[str, dict] = {}
    for name, unsorted in scenes.items():
        frames = sorted(unsorted, key=lambda frame: (frame.timestamp, frame.token))
        keys = [frame for frame in frames if frame.is_key_frame]
        if not keys:
            raise InputError(f"{folder}: scene {name!r} has no keyframe; a nuScenes scene needs at least one sample")
        scene_token = derive_token("scene", name)
        samples = [derive_token("sample", frame.token) for frame in keys]
        tables["scene"].append({
            "token": scene_token, "log_token": log_token, "nbr_samples": len(keys), "first_sample_token": samples[0],
            "last_sample_token": samples[-1], "name": name, "description": "",
        })  # fmt: skip
        for i, (frame, token) in enumerate(zip(keys, samples)):
            tables["sample"].append({
                "token": token, "timestamp": frame.timestamp, "prev": samples[i - 1] if i else "",
                "next": samples[i + 1] if i + 1 < len(samples) else "", "scene_token": scene_token,
            })  # fmt: skip
        sample = samples[0]
        for i, frame in enumerate(frames):
            if frame.is_key_frame:
                sample = derive_token("sample", frame.token)
            translation, rotation = pose_parts(frame.lidar_to_ego)
            calibration = derive_token("calibrated_sensor", name, *translation, *rotation)
            calibrations.setdefault(calibration, {
                "token": calibration, "sensor_token": sensor_token, "translation": translation, "rotation": rotation,
                "camera_intrinsic": [],
            })  # fmt: skip
            translation, rotation = pose_parts(frame.ego_to_world)
            ego_pose = derive_token("ego_pose", frame.token)
            tables["ego_pose"].append(
                {"token": ego_pose, "timestamp": frame.timestamp, "rotation": rotation, "translation": translation}
            )
            tables["sample_data"].append({
                "token": frame.token, "sample_token": sample, "ego_pose_token": ego_pose,
                "calibrated_sensor_token": calibration, "timestamp": frame.timestamp, "fileformat": "pcd",
                "is_key_frame": frame.is_key_frame, "height": 0, "width": 0, "filename": frame.filename,
                "prev": frames[i - 1].token if i else "", "next": frames[i + 1].token if i + 1 < len(frames) else "",
            })  # fmt: skip
            if frame.lidarseg is not None:
                tables["lidarseg"].append(
                    {"token": frame.token, "sample_data_token": frame.token, "filename": frame.lidarseg}
                )
    tables["calibrated_sensor"] = list(calibrations.values())
    for name, records in tables.items():
        atomic_write_text(folder / f"{name}.json", json.dumps(records, indent=0) + "\n")
