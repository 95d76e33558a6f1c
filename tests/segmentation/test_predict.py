"""Per-point probability export (segmentation/predict.py; the contract with u4d_aug.uncertainty), test-time views
and readouts."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from segmentation.config import SegTrainConfig
from segmentation.evaluate import evaluate
from segmentation.metrics import ConfusionMatrix, mean_iou
from segmentation.predict import (
    add_seg_predict_arguments,
    checkpoint_hash,
    load_checkpoint,
    model_from_checkpoint,
    parse_sequences,
    predict_probs,
    predict_root,
    probs_path,
    run_seg_predict,
)
from segmentation.train import train
from tests.tiny_nets import SEG_TINY as TINY
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.formats import load_kitti_frame, read_kitti_scan, write_kitti_scan
from u4d_aug.data.labels import SEMANTICKITTI_IGNORE
from u4d_aug.errors import InputError
from u4d_aug.uncertainty import load_probs


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(toy root, model.pt of a 4-step tiny run on it)."""
    torch.set_num_threads(1)
    root = write_toy_root(tmp_path_factory.mktemp("toy"))
    out = tmp_path_factory.mktemp("run")
    cfg = load_config(SegTrainConfig, TINY, [f"data.root={root}", f"out_dir={out}", "optim.steps=4", "eval_every=4"])
    train(cfg, progress=False)
    return root, out / "model.pt"


def _predict_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_seg_predict_arguments(parser)
    return parser.parse_args(list(argv))


def test_predict_writes_float16_probs_in_scan_order_and_resumes(trained, tmp_path):
    root, ckpt = trained
    out = tmp_path / "probs"
    assert run_seg_predict(_predict_args(str(ckpt), str(root), "--out", str(out), "--no-progress")) == 0
    files = sorted(out.glob("sequences/*/probs/*.npy"))
    assert [f"{f.parent.parent.name}/{f.stem}" for f in files] == [
        f"{s}/{i:06d}" for s in ("00", "01") for i in range(3)
    ]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["checkpoint_sha256"] == checkpoint_hash(ckpt) and len(manifest["checkpoint_sha256"]) == 16
    assert manifest["complete"] and manifest["num_classes"] == 19 and manifest["dtype"] == "float16"
    assert manifest["config"]["model"]["voxel_size"] == 0.5

    # same rows as a direct forward of the scan, in the scan's point order
    model = model_from_checkpoint(load_checkpoint(ckpt), torch.device("cpu"))
    points = read_kitti_scan(root / "sequences" / "01" / "velodyne" / "000002.bin")
    probs = np.load(probs_path(out, "01", "000002"))
    assert probs.dtype == np.float16 and probs.shape == (len(points), 19)
    np.testing.assert_allclose(probs.astype(np.float32).sum(1), 1.0, atol=1e-2)
    np.testing.assert_allclose(probs, predict_probs(model, points, torch.device("cpu")).numpy(), atol=1e-3)
    # permuting the points permutes the rows
    perm = np.random.default_rng(0).permutation(len(points))
    np.testing.assert_allclose(predict_probs(model, points[perm], torch.device("cpu")).numpy(), probs[perm], atol=1e-3)

    # resumable: existing files are skipped, a missing one is rewritten
    probs_path(out, "00", "000001").unlink()
    stamp = probs_path(out, "01", "000000").stat().st_mtime_ns
    result = predict_root(ckpt, root, out, progress=False)
    assert (result["written"], result["skipped"]) == (1, 5)
    assert probs_path(out, "01", "000000").stat().st_mtime_ns == stamp


def test_predict_refuses_to_mix_checkpoints_and_drops_nan_points(trained, tmp_path):
    root, ckpt = trained
    out = tmp_path / "probs"
    predict_root(ckpt, root, out, sequences=["01"], progress=False)
    other = tmp_path / "other.pt"
    state = torch.load(ckpt, weights_only=True)
    state["step"] = 99
    torch.save(state, other)
    with pytest.raises(InputError, match="manifest.json"):
        predict_root(other, root, out, sequences=["01"], progress=False)

    # a NaN point is dropped with a counted warning: the rows follow the points every reader of the scan sees
    # (load_kitti_frame drops them too), so U4D's load_probs(path, len(points)) matches
    nan_root = tmp_path / "nan"
    points = read_kitti_scan(root / "sequences" / "00" / "velodyne" / "000000.bin").copy()
    points[5] = np.nan
    points[6, :3] = 3e38  # finite, but a voxel grid would overflow: NaN probabilities if it were kept
    points[7, 0] = 2e4  # 20 km: no sensor's return
    write_kitti_scan(nan_root / "sequences" / "00" / "velodyne" / "000000.bin", points)
    with pytest.warns(UserWarning, match=r"dropped 3 of 3000 points \(1 with NaN/inf values, 2 beyond 10000 m\)"):
        predict_root(ckpt, nan_root, tmp_path / "nan_probs", progress=False)
    kept = load_kitti_frame(nan_root / "sequences" / "00" / "velodyne" / "000000.bin").points
    probs = load_probs(probs_path(tmp_path / "nan_probs", "00", "000000"), len(kept)).astype(np.float32)
    assert probs.shape == (len(points) - 3, 19) and np.isfinite(probs).all()


def test_a_checkpoint_of_another_kind_is_refused_in_one_line(trained, tmp_path):
    root, ckpt = trained
    state = torch.load(ckpt, weights_only=True)
    diffusion = {"kind": "u4d-diffusion", "config": {"net": {}}, "model": state["model"], "step": 4}
    torch.save(diffusion, tmp_path / "diffusion.pt")
    with pytest.raises(InputError, match="diffusion.pt: not a segmentation checkpoint \\(a u4d-diffusion checkpoint"):
        predict_root(tmp_path / "diffusion.pt", root, tmp_path / "o", progress=False)
    wrong = {**state, "model": {key: value.reshape(-1)[:1] for key, value in state["model"].items()}}
    torch.save(wrong, tmp_path / "wrong.pt")
    with pytest.raises(InputError, match=r"wrong.pt: its weights do not fit the net \(\S+: shape \(1,\) here, \("):
        predict_root(tmp_path / "wrong.pt", root, tmp_path / "o", progress=False)


def test_predict_rejects_bad_inputs(trained, tmp_path):
    root, ckpt = trained
    with pytest.raises(InputError, match="checkpoint not found"):
        predict_root(tmp_path / "missing.pt", root, tmp_path / "o", progress=False)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="junk.pt"):
        predict_root(tmp_path / "junk.pt", root, tmp_path / "o", progress=False)
    with pytest.raises(InputError, match="07"):
        predict_root(ckpt, root, tmp_path / "o", sequences=["07"], progress=False)


def test_views_average_the_softmax_over_mirror_and_turned_views(trained, tmp_path):
    """Test-time augmentation: views=k is the mean of the single-view softmax of the first k mirror / turned views."""
    root, ckpt = trained
    model = model_from_checkpoint(load_checkpoint(ckpt), torch.device("cpu"))
    points = torch.from_numpy(read_kitti_scan(root / "sequences" / "00" / "velodyne" / "000001.bin").copy())
    cpu = torch.device("cpu")
    signs = [(1, 1), (-1, 1), (1, -1), (-1, -1)]
    single = []
    for sx, sy in signs:
        view = points.clone()
        view[:, 0] *= sx
        view[:, 1] *= sy
        single.append(predict_probs(model, view, cpu))  # (N, K)
    assert not torch.allclose(single[0], single[1], atol=1e-4)  # the mirror views do change the prediction
    for views in (1, 2, 4):
        expected = torch.stack(single[:views]).mean(dim=0)
        torch.testing.assert_close(predict_probs(model, points, cpu, views), expected, atol=1e-5, rtol=1e-4)
    # views 8 adds the four mirrors turned by 45 degrees about z: another voxel grid, another prediction
    c = math.sqrt(0.5)
    turned = []
    for sx, sy in signs:
        x, y = points[:, 0] * sx, points[:, 1] * sy
        view = points.clone()
        view[:, 0], view[:, 1] = c * (x - y), c * (x + y)
        turned.append(predict_probs(model, view, cpu))
    assert not torch.allclose(turned[0], single[0], atol=1e-4)
    expected = torch.stack(single + turned).mean(dim=0)
    torch.testing.assert_close(predict_probs(model, points, cpu, 8), expected, atol=1e-5, rtol=1e-4)
    assert torch.equal(points, torch.from_numpy(read_kitti_scan(root / "sequences" / "00" / "velodyne" / "000001.bin")))

    # seg-eval scores the averaged probabilities; seg-predict records the views and refuses to mix two counts
    summary = evaluate(ckpt, root, ["00"], views=2)
    cm = ConfusionMatrix(19, SEMANTICKITTI_IGNORE)
    for item in ScanDataset(root, ["00"]):
        cm.update(predict_probs(model, item["points"], cpu, 2).argmax(1), item["labels"])
    assert summary["views"] == 2 and summary["miou"] == pytest.approx(mean_iou(cm.matrix))
    out = tmp_path / "probs"
    assert run_seg_predict(_predict_args(str(ckpt), str(root), "--out", str(out), "--views", "4", "--no-progress")) == 0
    assert json.loads((out / "manifest.json").read_text())["views"] == 4
    probs = np.load(probs_path(out, "00", "000001")).astype(np.float32)
    np.testing.assert_allclose(probs, torch.stack(single).mean(dim=0).numpy(), atol=2e-3)
    with pytest.raises(InputError, match="--views 4, not 1"):
        predict_root(ckpt, root, out, progress=False)
    for bad in (0, 5, 36):
        with pytest.raises(InputError, match="--views must be 1-4"):
            evaluate(ckpt, root, ["00"], views=bad)


def test_cli_sequence_ranges() -> None:
    assert parse_sequences(["88-99"]) == ["88-99"]  # expanded by resolve_sequences
    assert parse_sequences(["00-02,05", "07"]) == ["00-02", "05", "07"]
    assert parse_sequences(["train"]) == "train" and parse_sequences(None) is None


def test_readout_override_in_eval_and_predict(trained, tmp_path):
    """--readout trilinear rereads the same weights (a MinkUNet checkpoint trained with the voxel readout):
    seg-eval scores the interpolated softmax and records the readout; seg-predict will not mix two readouts."""
    root, ckpt = trained
    cpu = torch.device("cpu")
    voxel = model_from_checkpoint(load_checkpoint(ckpt), cpu)
    trilinear = model_from_checkpoint(load_checkpoint(ckpt), cpu, readout="trilinear")
    assert (voxel.cfg.readout, trilinear.cfg.readout) == ("voxel", "trilinear")
    points = torch.from_numpy(read_kitti_scan(root / "sequences" / "00" / "velodyne" / "000001.bin").copy())
    a, b = predict_probs(voxel, points, cpu), predict_probs(trilinear, points, cpu)
    assert not torch.allclose(a, b, atol=1e-4)  # points near voxel borders read their neighbours too
    torch.testing.assert_close(b.sum(dim=1), torch.ones(b.shape[0]))
    summary = evaluate(ckpt, root, ["00"], readout="trilinear")
    cm = ConfusionMatrix(19, SEMANTICKITTI_IGNORE)
    for item in ScanDataset(root, ["00"]):
        cm.update(predict_probs(trilinear, item["points"], cpu).argmax(1), item["labels"])
    assert summary["readout"] == "trilinear" and summary["miou"] == pytest.approx(mean_iou(cm.matrix))
    out = tmp_path / "probs"
    args = ("--out", str(out), "--sequences", "00", "--no-progress")
    assert run_seg_predict(_predict_args(str(ckpt), str(root), *args, "--readout", "trilinear")) == 0
    assert json.loads((out / "manifest.json").read_text())["readout"] == "trilinear"
    with pytest.raises(InputError, match="readout trilinear, not voxel"):
        predict_root(ckpt, root, out, sequences=["00"], progress=False)
