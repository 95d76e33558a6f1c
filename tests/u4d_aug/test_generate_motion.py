"""`u4d generate` of ego-motion-conditioned sequences: trajectories from a file or the training sequences, poses.txt."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.tiny_nets import PLAIN_SAMPLING, TINY_MOST, save_checkpoint
from tests.tiny_worlds import REAL_ROOT, write_tiny_world
from u4d_aug.bank import BankLayout, write_sample, write_sequence_poses
from u4d_aug.config import load_config
from u4d_aug.data.formats import read_calib, read_kitti_scan, read_poses, write_calib, write_poses
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, generate_bank, load_motion_file
from u4d_aug.metrics.evaluate import evaluate
from u4d_aug.metrics.temporal import load_kitti_sequence, ttce
from u4d_aug.trajectory import poses_from_motion, relative_motion, straight_motion

REAL_SCAN = REAL_ROOT / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin"


def world_poses(num_scans: int) -> np.ndarray:
    """(T, 4, 4) LiDAR poses of an uneven drive (varying speed and turn, climbing), so every window differs."""
    rng = np.random.default_rng(3)
    track = np.zeros((num_scans, 4))
    track[:, 0] = np.cumsum(rng.uniform(0.5, 2.0, num_scans)) - 1.0
    track[:, 1] = rng.uniform(-0.3, 0.3, num_scans)
    track[:, 2] = 0.05 * np.arange(num_scans)
    track[:, 3] = np.cumsum(rng.uniform(-0.2, 0.2, num_scans))
    return poses_from_motion(track, poses_from_motion(np.array([[3.0, 4.0, 0.0, 1.0]]))[0])


def write_checkpoint(path: Path, stage: str, data_root: Path, *extra: str) -> Path:
    """An untrained tiny MoST checkpoint (2-frame windows) whose config trains on data_root."""
    return save_checkpoint(path, TINY_MOST, (f"diffusion.stage={stage}", f"data_root={data_root}", *extra))


@pytest.fixture(scope="module")
def posed(tmp_path_factory) -> dict:
    """A tiny world of 6 scans with poses.txt + calib.txt (a non-identity Tr) and pose-conditioned checkpoints."""
    root = tmp_path_factory.mktemp("posed")
    world = root / "world"
    write_tiny_world(world, root / "probs", num_scans=6, num_points=500)
    folder = world / "sequences" / "00"
    tr = np.eye(4)
    tr[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]  # KITTI-like velodyne -> cam0 axes
    tr[:3, 3] = [0.1, -0.05, -0.3]
    calib = {"P0": np.eye(4)[:3], "Tr": tr[:3]}
    write_calib(folder / "calib.txt", calib)
    poses = world_poses(6)
    write_poses(folder / "poses.txt", poses, calib)
    paths = {
        s: write_checkpoint(root / f"{s}.pt", s, world, "net.pose_dim=4") for s in ("stage1", "stage2", "baseline")
    }
    bare = root / "bare"  # a world without poses: no trajectory source
    write_tiny_world(bare, root / "bare_probs", num_scans=3, num_points=200)
    paths["no_source"] = write_checkpoint(root / "no_source.pt", "baseline", bare, "net.pose_dim=4")
    paths["unposed"] = write_checkpoint(root / "unposed.pt", "baseline", world)
    return {"paths": paths, "poses": poses, "world": world, "probs": root / "probs"}


def gen_config(posed: dict, *overrides: str) -> GenerateConfig:
    paths = posed["paths"]
    base = [f"stage1={paths['stage1']}", f"stage2={paths['stage2']}", f"baseline={paths['baseline']}"]
    base += ["steps=2", "sampler=ddim", *PLAIN_SAMPLING, "device=cpu", "seed=7"]
    return load_config(GenerateConfig, None, [*base, *overrides])


def bank_motion(layout: BankLayout, index: int) -> np.ndarray:
    """(L, 4) motion of bank sequence `index`, read back from its poses.txt with its calib.txt."""
    return relative_motion(read_poses(layout.poses_path(index), read_calib(layout.calib_path(index))))


def test_a_straight_line_from_a_motion_file_is_written_as_exactly_those_poses(posed, tmp_path):
    motion = straight_motion(5, 0.7)  # 5 frames, 0.7 m per frame straight ahead
    np.save(tmp_path / "straight.npy", motion)
    bank = tmp_path / "bank"
    manifest = generate_bank(
        gen_config(posed, "num=2", "frames=5", f"motion_file={tmp_path / 'straight.npy'}"), bank, progress=False
    )
    layout = BankLayout(bank, 5)
    assert manifest["complete"] and manifest["samples"][1]["motion"] == {
        "file": str(tmp_path / "straight.npy"),
        "row": 0,
    }
    for index in range(2):
        written = read_poses(layout.poses_path(index), read_calib(layout.calib_path(index)))
        np.testing.assert_allclose(written, poses_from_motion(motion), atol=1e-6)
        np.testing.assert_allclose(bank_motion(layout, index), motion, atol=1e-5)
        assert all(layout.scan_path(index, f).is_file() or layout.is_empty(index, f) for f in range(5))
    assert "poses.txt" in " ".join(manifest["samples"][0]["sha256"])  # the poses are part of the sample's record
    temporal = evaluate(bank, posed["world"], metrics=("ttce", "ctc"))["table2"]["bank"]  # `u4d evaluate`
    assert "missing" not in temporal, temporal
    assert temporal["ttce_pairs"] == {"3": 4, "4": 2} and None not in temporal["ttce"].values(), temporal


def test_trajectories_are_windows_of_the_training_motion_whatever_the_batch(posed, tmp_path):
    real = posed["poses"]  # (6, 4, 4) LiDAR poses of the training world
    windows = {f"00/{s:06d}": relative_motion(real[s : s + 2]) for s in range(5)}
    banks = {}
    for batch_size in (1, 3):
        out = tmp_path / f"bank_{batch_size}"
        manifest = generate_bank(
            gen_config(posed, "mode=baseline", "num=4", f"batch_size={batch_size}"), out, progress=False
        )
        layout = BankLayout(out, 2)
        drawn = [entry["motion"]["window"][0] for entry in manifest["samples"]]
        for index, start in enumerate(drawn):
            np.testing.assert_allclose(bank_motion(layout, index), windows[start], atol=1e-5)
        banks[batch_size] = (drawn, [layout.poses_path(i).read_bytes() for i in range(4)])
    assert banks[1] == banks[3]  # sample i's trajectory depends on seed + i only
    assert len(set(banks[1][0])) > 1  # different samples drive different windows
    assert manifest["motion"] == "training sequences"  # part of the identity a re-run must match


def test_ttce_of_one_real_scan_moved_along_known_poses_is_zero(tmp_path):
    if not REAL_SCAN.is_file():
        pytest.skip(f"{REAL_SCAN}: real SemanticKITTI scan not present")
    scan = read_kitti_scan(REAL_SCAN)  # the static world, seen from frame 0
    # KITTI pace (0.7 m and 0.01 rad per frame): ICP from the identity with 2 m correspondences does not reach
    # 4 m apart (1 m per frame: k = 4 gives 0.42 m) or sharper turns (0.03 rad per frame: 0.39 m)
    motion = straight_motion(5, 0.7, yaw_rate=0.01)
    poses = poses_from_motion(motion)  # (5, 4, 4) sensor -> world (= frame 0)
    layout = BankLayout(tmp_path / "moved", 5)
    write_sequence_poses(layout, 0, poses)
    for frame, pose in enumerate(poses):
        inverse = np.linalg.inv(pose)
        moved = scan.copy()
        moved[:, :3] = scan[:, :3] @ inverse[:3, :3].T + inverse[:3, 3]  # world points in frame l's sensor frame
        write_sample(layout, 0, moved, frame=frame)
    scans, read_back = load_kitti_sequence(layout.sequence_dir(0))
    np.testing.assert_allclose(read_back, poses, atol=1e-6)
    scores = ttce(scans, read_back)
    assert scores.mean[3] < 0.01 and scores.mean[4] < 0.01, scores.mean  # measured: 1.1 / 0.5 mm


def test_a_pose_conditioned_bank_without_a_trajectory_source_is_one_input_error(posed, tmp_path):
    paths = posed["paths"]
    with pytest.raises(InputError, match="motion_file") as caught:
        generate_bank(
            gen_config(posed, "mode=baseline", f"baseline={paths['no_source']}", "num=1"),
            tmp_path / "a",
            progress=False,
        )
    assert "\n" not in str(caught.value) and "poses.txt" in str(caught.value)
    with pytest.raises(InputError, match="no ego-motion input"):
        np.save(tmp_path / "m.npy", straight_motion(2, 1.0))
        generate_bank(
            gen_config(posed, "mode=baseline", f"baseline={paths['unposed']}", f"motion_file={tmp_path / 'm.npy'}"),
            tmp_path / "b",
            progress=False,
        )


def test_unposed_sequence_nets_write_only_placeholder_poses(posed, tmp_path):
    manifest = generate_bank(
        gen_config(posed, "mode=baseline", f"baseline={posed['paths']['unposed']}", "num=1"),
        tmp_path / "c",
        progress=False,
    )
    layout = BankLayout(tmp_path / "c", 2)
    assert layout.is_done(0) and manifest["placeholder_poses"]  # identity poses.txt for readers, no ground truth
    np.testing.assert_array_equal(read_poses(layout.poses_path(0)), np.broadcast_to(np.eye(4), (2, 4, 4)))
    assert "motion" not in manifest and "motion" not in manifest["samples"][0]


def test_motion_files(tmp_path):
    motions = np.stack([straight_motion(3, 1.0), straight_motion(3, 2.0, yaw_rate=0.1)])
    np.save(tmp_path / "two.npy", motions)
    assert load_motion_file(tmp_path / "two.npy", 3).shape == (2, 3, 4)
    with pytest.raises(InputError, match=r"expected \(2, 4\)"):
        load_motion_file(tmp_path / "two.npy", 2)
    poses = poses_from_motion(motions[1], poses_from_motion(np.array([[5.0, -2.0, 1.0, 2.0]]))[0])
    write_poses(tmp_path / "poses.txt", poses)  # no calib.txt beside it: LiDAR poses as they are
    np.testing.assert_allclose(load_motion_file(tmp_path / "poses.txt", 3)[0], motions[1], atol=1e-5)
    with pytest.raises(InputError, match="3 poses"):
        load_motion_file(tmp_path / "poses.txt", 4)


def test_completion_conditions_on_the_real_frames_motion(posed, tmp_path):
    real = {"mode=complete", f"data_root={posed['world']}", f"probs_root={posed['probs']}", "num=2"}
    manifest = generate_bank(gen_config(posed, *sorted(real)), tmp_path / "bank", progress=False)
    layout = BankLayout(tmp_path / "bank", 2)
    for index in range(2):  # sample i completes window i and keeps its poses (relative to its first frame)
        np.testing.assert_allclose(
            bank_motion(layout, index), relative_motion(posed["poses"][index : index + 2]), atol=1e-5
        )
    assert manifest["complete"] and "motion" not in manifest["samples"][0]
    np.save(tmp_path / "m.npy", straight_motion(2, 1.0))
    with pytest.raises(InputError, match="completion mode"):
        generate_bank(gen_config(posed, *sorted(real), f"motion_file={tmp_path / 'm.npy'}"), tmp_path / "x")


def test_propagated_banks_move_frame_0_along_the_written_poses(posed, tmp_path):
    motion = straight_motion(3, 1.0)
    np.save(tmp_path / "straight.npy", motion)
    bank = tmp_path / "bank"
    overrides = ("num=1", "frames=3", f"motion_file={tmp_path / 'straight.npy'}", "propagate=true")
    manifest = generate_bank(gen_config(posed, *overrides), bank, progress=False)
    assert manifest["complete"]
    layout = BankLayout(bank, 3)
    plain = tmp_path / "plain"
    generate_bank(gen_config(posed, *overrides[:-1]), plain, progress=False)
    with pytest.raises(InputError, match="different sampling"):  # one bank, one way of generating
        generate_bank(gen_config(posed, *overrides[:-1]), bank, progress=False)
    with pytest.raises(InputError, match="different sampling"):
        generate_bank(gen_config(posed, *overrides), plain, progress=False)
    baseline = generate_bank(gen_config(posed, "mode=baseline", *overrides), tmp_path / "b", progress=False)
    assert baseline["complete"] and baseline["sampling"]["propagate"] is True
    with pytest.raises(InputError, match="propagate: moves frame 0"):
        unposed = ("mode=baseline", f"baseline={posed['paths']['unposed']}", "frames=3", "propagate=true")
        generate_bank(gen_config(posed, *unposed), tmp_path / "c", progress=False)  # nothing to move frame 0 along
    written = read_poses(layout.poses_path(0), read_calib(layout.calib_path(0)))
    np.testing.assert_allclose(written, poses_from_motion(motion), atol=1e-6)
    assert layout.scan_path(0, 2).is_file() or layout.is_empty(0, 2)


def test_pinned_propagation_is_its_own_way_of_generating_and_needs_propagation(posed, tmp_path):
    np.save(tmp_path / "straight.npy", straight_motion(3, 1.0))
    overrides = ("num=1", "frames=3", f"motion_file={tmp_path / 'straight.npy'}", "propagate=true")
    pinned = generate_bank(gen_config(posed, *overrides, "propagate_pin=true"), tmp_path / "pinned", progress=False)
    assert pinned["complete"] and pinned["sampling"]["propagate_pin"] is True
    plain = tmp_path / "plain"
    assert "propagate_pin" not in generate_bank(gen_config(posed, *overrides), plain, progress=False)["sampling"]
    # (what pinning changes in the fill: tests/u4d_aug/test_pipeline.py, on nets whose output depends on x_t)
    with pytest.raises(InputError, match="different sampling"):
        generate_bank(gen_config(posed, *overrides, "propagate_pin=true"), plain, progress=False)
    baseline = generate_bank(gen_config(posed, "mode=baseline", *overrides, "propagate_pin=true"), tmp_path / "b")
    assert "propagate_pin" not in baseline["sampling"]  # the baseline's inpainting pins them anyway
    with pytest.raises(InputError, match="propagate_pin: pins stage 2"):
        generate_bank(gen_config(posed, *overrides[:-1], "propagate_pin=true"), tmp_path / "bad", progress=False)
