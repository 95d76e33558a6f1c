"""Simulated worlds written to disk (u4d_aug/data/sim/writer.py): determinism and resume, layout, poses, labels,
the command, the manifest, the sensor's intensity response."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.distance import jensenshannon

from tests.tiny_nets import REPO
from u4d_aug.config import config_to_dict, load_config
from u4d_aug.data.formats import (
    read_calib,
    read_kitti_label,
    read_kitti_scan,
    read_nuscenes_scan,
    read_poses,
    read_times,
)
from u4d_aug.data.labels import SEMANTICKITTI_RAW_NAMES, map_semantickitti
from u4d_aug.data.sensors import hdl32, hdl64, intensity_response
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.geometry import RAW
from u4d_aug.data.sim.report import INTENSITY_BINS
from u4d_aug.data.sim.scenes import STREET_TYPES
from u4d_aug.data.sim.writer import (
    add_simulate_arguments,
    build_sequence,
    config_argument,
    render_frame,
    run_simulate,
    simulate,
)
from u4d_aug.errors import InputError

TINY = REPO / "configs" / "sim" / "tiny.yaml"


def _tiny(*overrides: str) -> SimConfig:
    return load_config(SimConfig, TINY, overrides)


def _hashes(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "a"
    simulate(out, sequences=1, frames=3, seed=7, config=_tiny(), progress=False)
    return out


def test_same_seed_byte_identical_and_resume(tiny_world: Path, tmp_path: Path) -> None:
    again = tmp_path / "b"
    simulate(again, sequences=1, frames=3, seed=7, config=_tiny(), progress=False)
    first = _hashes(tiny_world)
    assert first == _hashes(again)
    assert {"manifest.json", "sequences/00/poses.txt", "sequences/00/velodyne/000002.bin"} <= set(first)
    # a re-run resumes: a deleted frame is rewritten identically, the rest is skipped
    (again / "sequences/00/velodyne/000001.bin").unlink()
    summary = simulate(again, sequences=1, frames=3, seed=7, config=_tiny(), progress=False)
    assert summary["written"] == 1 and summary["skipped"] == 2
    assert _hashes(again) == first


def test_different_seed_differs(tiny_world: Path, tmp_path: Path) -> None:
    other = tmp_path / "c"
    simulate(other, sequences=1, frames=1, seed=8, config=_tiny(), progress=False)
    a = read_kitti_scan(tiny_world / "sequences/00/velodyne/000000.bin")
    b = read_kitti_scan(other / "sequences/00/velodyne/000000.bin")
    assert a.shape != b.shape or not np.array_equal(a, b)


def test_resume_with_other_settings_is_refused(tiny_world: Path) -> None:
    with pytest.raises(InputError, match="seed"):
        simulate(tiny_world, sequences=1, frames=3, seed=99, config=_tiny(), progress=False)


def test_layout_poses_times_labels(tiny_world: Path) -> None:
    seq = tiny_world / "sequences" / "00"
    poses = read_poses(seq / "poses.txt", read_calib(seq / "calib.txt"))
    built = build_sequence(7, 0, 3, hdl64(), _tiny())
    expected = np.linalg.inv(built.ego.poses[0]) @ built.ego.poses
    np.testing.assert_allclose(poses, expected, atol=1e-9)
    np.testing.assert_allclose(read_times(seq / "times.txt"), [0.0, 0.1, 0.2])
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * 10.0
    assert np.all((step > 4.5) & (step < 12.5)), step  # ego speed 5-12 m/s
    points = read_kitti_scan(seq / "velodyne" / "000000.bin")
    semantic, instance = read_kitti_label(seq / "labels" / "000000.label", len(points))
    assert points.dtype == np.float32 and points.shape[1] == 4
    assert points[:, 3].min() >= 0.0 and points[:, 3].max() <= 1.0
    assert set(np.unique(semantic).tolist()) <= set(SEMANTICKITTI_RAW_NAMES)
    r = np.linalg.norm(points[:, :3], axis=1)
    assert r.min() >= hdl64().min_range and r.max() <= hdl64().max_range
    # road under the sensor at about -sensor_height
    road = (semantic == 40) & (r < 15)
    assert abs(np.median(points[road, 2]) + 1.80) < 0.05
    # the labels stop at label_range (50 m), as in the real seq-00 frames
    assert np.all(semantic[r > 50.5] == 0) and np.all(instance[r > 50.5] == 0)
    assert np.mean(semantic[r < 49.5] == 0) < 0.01


def test_ring_major_storage_order() -> None:
    seq = build_sequence(3, 0, 1, hdl64(), _tiny())
    scan = render_frame(seq, 0)
    assert np.all(np.diff(scan.ring) >= 0)  # top ring first
    ring = scan.ring == 40
    azimuth = np.mod(np.arctan2(scan.points[ring, 1], scan.points[ring, 0]), 2 * np.pi)
    assert np.all(np.diff(azimuth) > -1e-3)  # counter-clockwise from the front


def test_static_points_align_with_poses(tmp_path: Path) -> None:
    out = tmp_path / "dense"
    simulate(out, 1, 3, seed=5, config=_tiny("lidar.azimuth_steps=2083"), progress=False)
    seq = out / "sequences" / "00"
    poses = read_poses(seq / "poses.txt", read_calib(seq / "calib.txt"))
    world = []
    for f in range(3):
        pts = read_kitti_scan(seq / "velodyne" / f"{f:06d}.bin")
        sem, _ = read_kitti_label(seq / "labels" / f"{f:06d}.label", len(pts))
        keep = (sem < 252) & (sem != 30) & (np.linalg.norm(pts[:, :3], axis=1) < 40)
        xyz = pts[keep, :3].astype(np.float64)
        world.append(xyz @ poses[f][:3, :3].T + poses[f][:3, 3])
    # frame 1 against its neighbours 0 and 2: ground rings sweep ~1 m per frame, so one neighbour alone leaves
    # gaps of half a ring spacing (the real seq-00 scans give 5.4 cm for 1 -> 0 in SOURCES.md)
    dist, _ = cKDTree(np.concatenate([world[0], world[2]])).query(world[1])
    assert np.median(dist) <= 0.05, np.median(dist)
    # a 10 cm pose error (height: most points are ground, which hides horizontal shifts) is clearly visible
    shifted, _ = cKDTree(np.concatenate([world[0], world[2]])).query(world[1] + [0.0, 0.0, 0.1])
    assert np.median(shifted) > np.median(dist) + 0.02


def test_cli_arguments(tmp_path: Path, capsys, caplog) -> None:
    caplog.set_level(logging.INFO, logger="u4d_aug.data.sim.writer")
    parser = argparse.ArgumentParser()
    add_simulate_arguments(parser)
    args = parser.parse_args(
        [
            "--out",
            str(tmp_path / "cli"),
            "--frames",
            "1",
            "--seed",
            "2",
            "--config",
            str(TINY),
            "--set",
            "agents.pedestrians_per_100m=0",
        ]
    )
    assert run_simulate(args) == 0
    assert "wrote 1 frames" in capsys.readouterr().out
    # it says which preset wrote the world, and records it
    said = f"world of {TINY}, overrides agents.pedestrians_per_100m=0 (recorded in manifest.json)"
    assert any(said in message for message in caplog.messages), caplog.messages
    manifest = json.loads((tmp_path / "cli" / "manifest.json").read_text())
    assert manifest["config_source"] == {"config": str(TINY), "overrides": ["agents.pedestrians_per_100m=0"]}
    with pytest.raises(InputError, match="unknown config key"):
        load_config(SimConfig, None, ["lidar.nope=1"])


def test_the_config_is_positional_and_config_is_its_alias(tmp_path: Path) -> None:
    from u4d_aug.cmdline import CommandParser, parse_command_line

    parser = CommandParser(prog="u4d simulate")
    add_simulate_arguments(parser)
    out = tmp_path / "world"
    argv = ["sim/tiny", "--out", str(out), "--frames", "1", "--no-progress", "agents.pedestrians_per_100m=0"]
    args = parse_command_line(parser, argv)
    assert (args.preset, args.config, args.overrides) == (Path("sim/tiny"), None, ["agents.pedestrians_per_100m=0"])
    assert run_simulate(args) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config_source"] == {"config": "sim/tiny", "overrides": ["agents.pedestrians_per_100m=0"]}
    assert manifest["config"] == config_to_dict(_tiny("agents.pedestrians_per_100m=0"))  # the preset was read
    # --config names the same file: fine; another one: refused before anything is written
    assert config_argument(Path("sim/tiny"), TINY) == Path("sim/tiny")
    assert config_argument(None, Path("sim/tiny")) == Path("sim/tiny") and config_argument(None, None) is None
    other = parse_command_line(parser, ["sim/tiny", "--config", "sim/seg_rich", "--out", str(tmp_path / "other")])
    with pytest.raises(InputError, match="simulate: config sim/tiny and --config sim/seg_rich name different files"):
        run_simulate(other)
    assert not (tmp_path / "other").exists()


@pytest.mark.slow
def test_default_hdl64_frame_point_count() -> None:
    seq = build_sequence(0, 0, 1, hdl64(), SimConfig())
    scan = render_frame(seq, 0)
    assert 100_000 <= len(scan.points) <= 135_000, len(scan.points)


@pytest.mark.slow
def test_four_sequences_cover_fifteen_classes(tmp_path: Path) -> None:
    cfg = SimConfig()
    present = set()
    for index in range(4):
        seq = build_sequence(1, index, 6, hdl64(), cfg)
        for frame in (0, 5):
            present |= set(np.unique(map_semantickitti(render_frame(seq, frame).semantic)).tolist())
    present.discard(19)
    assert len(present) >= 15, sorted(present)


def _instances(mesh, label: str) -> int:
    return len(np.unique(mesh.instance[mesh.semantic == RAW[label]]))


def test_rich_preset_makes_rare_classes_frequent() -> None:
    rich = load_config(SimConfig, REPO / "configs" / "sim" / "seg_rich.yaml", [])
    counts = {"default": {}, "rich": {}}
    for name, cfg in (("default", SimConfig()), ("rich", rich)):
        for index in range(3):
            seq = build_sequence(5, index, 3, hdl64(), cfg)
            for label in ("truck", "other-vehicle", "motorcycle", "bicycle"):
                counts[name][label] = counts[name].get(label, 0) + _instances(seq.world.mesh, label)
            for agent in seq.agents:
                counts[name][agent.kind] = counts[name].get(agent.kind, 0) + 1
    for key in ("truck", "other-vehicle", "motorcycle", "bicycle", "person", "bicyclist", "motorcyclist"):
        assert counts["rich"].get(key, 0) > 1.5 * counts["default"].get(key, 0), (key, counts)


def test_manifest_records_the_preset_and_the_street_types(tmp_path: Path) -> None:
    import json

    parser = argparse.ArgumentParser()
    add_simulate_arguments(parser)
    out = tmp_path / "varied"
    args = parser.parse_args(["--out", str(out), "--frames", "1", "--sequences", "3", "--config", "sim/varied"])
    args.overrides = ["view_radius=60", "lidar.azimuth_steps=360"]
    assert run_simulate(args) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config_source"] == {"config": "sim/varied", "overrides": args.overrides}
    assert manifest["config"]["street_types"]["park"] > 0
    assert len(manifest["street_types"]) == 3 and set(manifest["street_types"]) <= set(STREET_TYPES)


def test_resume_of_a_world_written_before_the_street_types(tmp_path: Path) -> None:
    import json

    out = tmp_path / "old"
    simulate(out, 1, 1, seed=2, config=_tiny(), progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    for section, key in (("street", "main_lanes"), ("lots", "driveway_prob"), ("agents", "agent_route_extra")):
        del manifest["config"][section][key]  # as main wrote it
    del manifest["config"]["street_types"]
    (out / "manifest.json").write_text(json.dumps(manifest))
    assert simulate(out, 1, 1, seed=2, config=_tiny(), progress=False)["skipped"] == 1
    with pytest.raises(InputError, match="'config' differs"):
        simulate(out, 1, 1, seed=2, config=_tiny("lots.driveway_prob=0.5"), progress=False)


def _identity(sensor):
    return dataclasses.replace(sensor, intensity_floor=0.0, intensity_gain=1.0, intensity_gamma=1.0)


def _hdl32_remission(sensor, places: int = 2) -> list:
    """Scans of `places` tiny places x 1 frame (seed 5) seen by `sensor`."""
    return [render_frame(build_sequence(5, k, 1, sensor, _tiny()), 0) for k in range(places)]


def test_intensity_response_changes_the_intensity_and_nothing_else() -> None:
    fitted, plain = _hdl32_remission(hdl32(), 1)[0], _hdl32_remission(_identity(hdl32()), 1)[0]
    np.testing.assert_array_equal(fitted.points[:, :3], plain.points[:, :3])  # same random numbers, same returns
    np.testing.assert_array_equal(fitted.semantic, plain.semantic)
    np.testing.assert_array_equal(fitted.points[:, 3], intensity_response(hdl32(), plain.points[:, 3]))
    assert np.median(fitted.points[:, 3]) < 0.1 < np.median(plain.points[:, 3])


def test_hdl32_remission_moves_towards_the_real_nuscenes_keyframe(real_root: Path) -> None:
    scan = next((real_root / "nuscenes_mmdet3d_demo").glob("**/LIDAR_TOP/*.pcd.bin"))

    def hist(values: np.ndarray) -> np.ndarray:
        bins = np.clip(np.searchsorted(INTENSITY_BINS, values, side="right") - 1, 0, len(INTENSITY_BINS) - 2)
        return np.bincount(bins, minlength=len(INTENSITY_BINS) - 1)

    real = hist(read_nuscenes_scan(scan).points[:, 3])
    js = {
        name: jensenshannon(hist(np.concatenate([s.points[:, 3] for s in _hdl32_remission(sensor)])), real, base=2)
        for name, sensor in (("identity", _identity(hdl32())), ("fitted", hdl32()))
    }
    assert js["identity"] > 0.6 and js["fitted"] < 0.3, js


def test_resume_of_an_hdl32_world_written_before_the_intensity_response_is_refused(tmp_path: Path) -> None:
    import json

    out = tmp_path / "old32"
    simulate(out, 1, 1, seed=2, sensor="hdl32", config=_tiny(), progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["sensor_intensity_response"] == [0.009, 1.08, 2.68]
    del manifest["sensor_intensity_response"]  # as main wrote it: the HDL-32E reported the remission
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="'sensor_intensity_response' differs"):
        simulate(out, 1, 1, seed=2, sensor="hdl32", config=_tiny(), progress=False)
