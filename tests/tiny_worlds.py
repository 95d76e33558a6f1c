"""Tiny made-up data shared by tests: a labelled toy SemanticKITTI root, a toy bank, a static posed world for the
feature extractors, a posed driving sequence, random-ray scans with class probabilities for the diffusion stages;
the real-scan folder."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from u4d_aug.bank import BankLayout, write_manifest, write_sample
from u4d_aug.data.formats import (
    read_kitti_scan,
    write_calib,
    write_kitti_label,
    write_kitti_scan,
    write_poses,
)
from u4d_aug.io import atomic_save_npy

# ../shared/data/real beside the checkout (research data that stays outside the repository); U4D_REAL_DATA points
# elsewhere, e.g. from a git worktree whose parent folder has no shared/
REAL_ROOT = Path(os.environ.get("U4D_REAL_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data" / "real")


def toy_scan(rng: np.random.Generator, num_points: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Ground plane = road (raw 40), a box = car (10), a wall = building (50), a few unlabeled points (0)."""
    n_road, n_car, n_wall = num_points // 2, num_points // 4, num_points // 5
    n_none = num_points - n_road - n_car - n_wall
    radius, angle = 20.0 * np.sqrt(rng.random(n_road)), 2 * np.pi * rng.random(n_road)
    road = np.stack([radius * np.cos(angle), radius * np.sin(angle), np.full(n_road, -1.7)], 1)
    centre = np.array([rng.uniform(4, 8), rng.uniform(-4, 4), -0.95])  # a 4 x 2 x 1.5 m box on the road
    face = rng.integers(0, 3, n_car)
    car = rng.uniform(-0.5, 0.5, (n_car, 3))
    car[np.arange(n_car), face] = np.where(rng.random(n_car) < 0.5, -0.5, 0.5)
    car = centre + car * np.array([4.0, 2.0, 1.5])
    wall_x = rng.uniform(-14, -10)
    wall = np.stack([np.full(n_wall, wall_x), rng.uniform(-10, 10, n_wall), rng.uniform(-1.7, 5, n_wall)], 1)
    none = rng.uniform([-20, -20, 3], [20, 20, 8], (n_none, 3))
    xyz = np.concatenate([road, car, wall, none]) + rng.normal(0, 0.02, (num_points, 3))
    intensity = np.concatenate(
        [np.full(n_road, 0.2), np.full(n_car, 0.6), np.full(n_wall, 0.4), np.full(n_none, 0.1)]
    ) + rng.normal(0, 0.02, num_points)
    raw = np.concatenate([np.full(n_road, 40), np.full(n_car, 10), np.full(n_wall, 50), np.zeros(n_none)])
    order = rng.permutation(num_points)
    points = np.concatenate([xyz, intensity[:, None]], 1)[order].astype(np.float32)
    return points, raw[order].astype(np.uint16)


def write_toy_root(root: Path, sequences: tuple[str, ...] = ("00", "01"), frames: int = 3, seed: int = 0) -> Path:
    """A tiny SemanticKITTI-layout root: len(sequences) x frames labeled scans of the toy scene."""
    rng = np.random.default_rng(seed)
    for seq in sequences:
        for frame in range(frames):
            points, raw = toy_scan(rng)
            write_kitti_scan(root / "sequences" / seq / "velodyne" / f"{frame:06d}.bin", points)
            write_kitti_label(root / "sequences" / seq / "labels" / f"{frame:06d}.label", raw)
    return root


def write_toy_bank(root: Path, num: int = 4, empty: tuple[int, ...] = (2,), seed: int = 0) -> Path:
    """A bank as `u4d generate` writes one: scans with their stage-1 side files, an empty marker, a manifest."""
    rng = np.random.default_rng(seed)
    layout = BankLayout(root)
    for i in range(num):
        points = np.zeros((0, 4), np.float32) if i in empty else toy_scan(rng, 500 + 100 * i)[0]
        mask = rng.random((16, 64)) < 0.2
        write_sample(layout, i, points, mask=mask, x0_u=np.full((2, 16, 64), -1.0, np.float32))
    write_manifest(root, {"mode": "u4d", "frames": 1, "samples": [{"index": i} for i in range(num)], "complete": True})
    return root


def write_tiny_root(root: Path, num_frames: int = 5, labels: bool = True, poses: bool = True, shift: float = 0.0):
    """Static synthetic world (ground z=-1.73 m, walls at y=+-10 m) seen from a sensor moving 1 m/frame along x."""
    rng = np.random.default_rng(0)
    gx, gy = np.meshgrid(np.arange(-40.0, 40.0, 1.0), np.arange(-40.0, 40.0, 1.0))
    ground = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -1.73)], axis=1)
    wx, wz = np.meshgrid(np.arange(-40.0, 40.0, 0.5), np.arange(-1.5, 3.0, 0.5))
    walls = np.concatenate(
        [np.stack([wx.ravel(), np.full(wx.size, side + shift), wz.ravel()], axis=1) for side in (-10.0, 10.0)]
    )
    world = np.concatenate([ground, walls])  # (N, 3)
    raw = np.concatenate([np.full(len(ground), 40), np.full(len(walls), 50)]).astype(np.uint16)  # road, building
    seq = root / "sequences" / "00"
    lidar_poses = np.repeat(np.eye(4)[None], num_frames, axis=0)
    for i in range(num_frames):
        lidar_poses[i, 0, 3] = float(i)
        xyz = world - lidar_poses[i, :3, 3]
        dist = np.linalg.norm(xyz, axis=1)
        keep = (dist > 2.0) & (dist < 70.0)
        points = np.concatenate([xyz[keep], rng.uniform(0.0, 1.0, (keep.sum(), 1))], axis=1).astype(np.float32)
        write_kitti_scan(seq / "velodyne" / f"{i:06d}.bin", points)
        if labels:
            write_kitti_label(seq / "labels" / f"{i:06d}.label", raw[keep])
    if poses:
        calib = {"P0": np.eye(4)[:3], "Tr": np.eye(4)[:3]}
        write_calib(seq / "calib.txt", calib)
        write_poses(seq / "poses.txt", lidar_poses, calib)
    return root


def read_scans(root: Path) -> list[np.ndarray]:
    """The scans of sequence 00 of `root`, in frame order."""
    return [read_kitti_scan(p) for p in sorted((root / "sequences" / "00" / "velodyne").glob("*.bin"))]


def write_posed_world(root: Path, probs_root: Path, num_scans: int = 3) -> np.ndarray:
    """Scans of one sequence driving along x (2 m per frame) with poses.txt, calib.txt and class probabilities;
    returns the LiDAR poses."""
    rng = np.random.default_rng(1)
    poses = np.tile(np.eye(4), (num_scans, 1, 1))
    poses[:, 0, 3] = 5.0 + 2.0 * np.arange(num_scans)
    tr = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.1], [1.0, 0.0, 0.0, -0.3]])  # KITTI-like Tr
    folder = root / "sequences" / "00"
    for i in range(num_scans):
        direction = rng.normal(size=(3000, 3))
        direction[:, 2] = np.abs(direction[:, 2]) * -0.2
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        xyz = direction * rng.uniform(3, 50, (3000, 1))
        points = np.concatenate([xyz, rng.uniform(0, 1, (3000, 1))], axis=1).astype(np.float32)
        write_kitti_scan(folder / "velodyne" / f"{i:06d}.bin", points)
        atomic_save_npy(probs_root / "sequences" / "00" / "probs" / f"{i:06d}.npy", rng.dirichlet(np.ones(5), 3000))
    write_calib(folder / "calib.txt", {"P0": np.eye(4)[:3], "Tr": tr})
    write_poses(folder / "poses.txt", poses, calib={"Tr": tr})
    return poses


def write_tiny_world(root: Path, probs_root: Path, num_scans: int = 3, num_points: int = 4000) -> None:
    """Scans of points on random rays within HDL-64's vertical FOV, 3-60 m, plus random class probabilities."""
    rng = np.random.default_rng(0)
    for i in range(num_scans):
        elevation = np.deg2rad(rng.uniform(-24.0, 2.0, num_points))
        azimuth = rng.uniform(-np.pi, np.pi, num_points)
        depth = rng.uniform(3.0, 60.0, num_points)
        xyz = np.stack(
            [
                depth * np.cos(elevation) * np.cos(azimuth),
                depth * np.cos(elevation) * np.sin(azimuth),
                depth * np.sin(elevation),
            ],
            axis=1,
        )
        points = np.concatenate([xyz, rng.uniform(0, 1, (num_points, 1))], axis=1).astype(np.float32)
        write_kitti_scan(root / "sequences" / "00" / "velodyne" / f"{i:06d}.bin", points)
        logits = rng.normal(size=(num_points, 5)) * 2
        probs = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
        atomic_save_npy(probs_root / "sequences" / "00" / "probs" / f"{i:06d}.npy", probs.astype(np.float16))
