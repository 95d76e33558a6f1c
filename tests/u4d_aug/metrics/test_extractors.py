"""FRD/FPD extractors: tiny training run, feature shapes, hashes, refused comparisons, FRD(x, x) = 0."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from tests.tiny_nets import EXTRACTOR_TINY as TINY_CONFIG
from tests.tiny_nets import extractor_config
from tests.tiny_worlds import read_scans, write_tiny_root
from u4d_aug.config import load_config
from u4d_aug.errors import InputError
from u4d_aug.metrics.extractors import (
    FRD_NUM_SAMPLES,
    ExtractorConfig,
    compare_results,
    extract_features,
    frd_sample_indices,
    load_config_dict,
    load_extractor,
    run_train_extractor,
    train_extractor,
    weights_hash,
)
from u4d_aug.metrics.frechet import frechet_from_features
from u4d_aug.validate import NonFiniteLossError


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """Both tiny extractors trained 3 steps on the synthetic root (module-scoped: trained once)."""
    torch.set_num_threads(1)
    base = tmp_path_factory.mktemp("extractors")
    root = write_tiny_root(base / "root")
    frd_path, frd_hash = train_extractor("frd", extractor_config(root, base / "out"))
    fpd_path, fpd_hash = train_extractor("fpd", extractor_config(root, base / "out"))
    return {"root": root, "base": base, "frd": (frd_path, frd_hash), "fpd": (fpd_path, fpd_hash)}


def test_training_writes_checkpoint_log_and_hash(trained):
    path, digest = trained["frd"]
    ckpt = torch.load(path, weights_only=False)
    assert re.fullmatch("[0-9a-f]{16}", digest) and ckpt["hash"] == digest
    cfg = load_config_dict(ckpt["config"], str(path))
    assert weights_hash("frd", cfg, ckpt["state_dict"]) == digest  # the hash of the weights written
    nudged = dict(ckpt["state_dict"])
    name = next(n for n, v in nudged.items() if v.is_floating_point())
    nudged[name] = nudged[name].clone()
    nudged[name].view(-1)[0] += 1e-3
    assert weights_hash("frd", cfg, nudged) != digest  # one weight changed: another hash
    assert (path.parent / "frd_log.jsonl").is_file() and (path.parent / "frd_config.yaml").is_file()
    extractor = load_extractor(path)
    assert extractor.hash == digest and extractor.kind == "frd"
    assert trained["fpd"][1] != digest


def test_feature_shapes_are_documented(trained):
    scans = read_scans(trained["root"])
    frd = load_extractor(trained["frd"][0])
    feats = extract_features(frd, scans, batch_size=2)
    assert feats["frd"].shape == (len(scans), FRD_NUM_SAMPLES)
    assert feats["frd_pooled"].shape == (len(scans), 8)  # tiny base_channels
    assert frd.feature_dims == {"frd": 4096, "frd_pooled": 8}
    fpd = load_extractor(trained["fpd"][0])
    feats_p = extract_features(fpd, scans, batch_size=3)
    assert feats_p["fpd"].shape == (len(scans), 32 + 16 + 8)  # G + F1 + F2 of the tiny config
    assert np.isfinite(feats["frd"]).all() and np.isfinite(feats_p["fpd"]).all()
    # batching does not change features (eval-mode batch norm)
    again = extract_features(frd, scans[:2], batch_size=1)
    np.testing.assert_allclose(again["frd"], feats["frd"][:2], rtol=1e-5, atol=1e-5)


def test_frd_of_identical_sets_is_zero(trained):
    feats = extract_features(load_extractor(trained["frd"][0]), read_scans(trained["root"]))["frd"]
    assert abs(frechet_from_features(feats, feats)) < 1e-8 * max(1.0, float(np.sum(feats**2)))


def test_same_seed_same_hash_other_seed_other_hash(trained, tmp_path):
    root = trained["root"]
    _, again = train_extractor("frd", extractor_config(root, tmp_path / "a"))
    _, other = train_extractor("frd", extractor_config(root, tmp_path / "b", seed=1))
    assert again == trained["frd"][1]
    assert other != again


def test_tampered_checkpoint_is_refused(trained, tmp_path):
    ckpt = torch.load(trained["frd"][0], weights_only=False)
    ckpt["hash"] = "0" * 16
    torch.save(ckpt, tmp_path / "bad.pt")
    with pytest.raises(InputError, match="does not match"):
        load_extractor(tmp_path / "bad.pt")
    with pytest.raises(InputError, match="not found"):
        load_extractor(tmp_path / "missing.pt")


def test_compare_results_refuses_different_extractors():
    a = {"table1": {"frd": {"value": 1.0, "extractor_hash": "a" * 16}, "jsd": {"value": 0.1}}}
    b = {"table1": {"frd": {"value": 3.0, "extractor_hash": "a" * 16}, "jsd": {"value": 0.2}}}
    assert compare_results(a, b) == pytest.approx({"frd": 2.0, "jsd": 0.1})
    c = {"table1": {"frd": {"value": 3.0, "extractor_hash": "b" * 16}}}
    with pytest.raises(InputError, match="extractor"):
        compare_results(a, c)


def test_sample_indices_follow_python_random_seed_0():
    import random

    state = random.getstate()
    expected = random.Random(0).sample(range(10000), 4096)
    assert frd_sample_indices(10000).tolist() == expected
    assert random.getstate() == state  # no global state touched
    with pytest.raises(InputError, match="fewer"):
        frd_sample_indices(100)


def test_cli_function_trains(tmp_path):
    import argparse

    from u4d_aug.metrics.extractors import add_train_extractor_arguments

    root = write_tiny_root(tmp_path / "root", num_frames=2)
    parser = argparse.ArgumentParser()
    add_train_extractor_arguments(parser)
    args = parser.parse_args(
        ["fpd", str(TINY_CONFIG), f"data.root={root}", f"out_dir={tmp_path / 'o'}", "train.steps=1"]
    )
    assert run_train_extractor(args) == 0
    assert (tmp_path / "o" / "fpd.pt").is_file()
    with pytest.raises(InputError, match="unknown config key"):
        run_train_extractor(parser.parse_args(["frd", str(TINY_CONFIG), "train.nope=1"]))


def test_hash_covers_input_geometry(trained):
    from u4d_aug.metrics.extractors import weights_hash

    ckpt = torch.load(trained["frd"][0], weights_only=False)
    cfg = extractor_config(trained["root"], trained["base"] / "out")
    assert weights_hash("frd", cfg, ckpt["state_dict"]) == trained["frd"][1]
    cfg.data.width = 256
    assert weights_hash("frd", cfg, ckpt["state_dict"]) != trained["frd"][1]


class _HeightRule(torch.nn.Module):
    """Fake FRD head: road below z = -1.6 m, building above (the tiny world exactly), or one constant class."""

    def __init__(self, max_range: float, constant: str | None = None) -> None:
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(1))  # gives the module a device
        self.max_range, self.constant = max_range, constant

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        from u4d_aug.data.labels import SEMANTICKITTI_CLASSES

        road, building = SEMANTICKITTI_CLASSES.index("road"), SEMANTICKITTI_CLASSES.index("building")
        is_road = x[:, 3] * self.max_range < -1.6 if self.constant is None else torch.full(x[:, 3].shape, True)
        out = torch.zeros(x.shape[0], len(SEMANTICKITTI_CLASSES), *x.shape[2:])
        out[:, road], out[:, building] = is_road.float(), (~is_road).float()
        return out


def test_heldout_scores_count_pixels_exactly(tmp_path):
    from u4d_aug.data.datasets import ScanDataset
    from u4d_aug.data.sensors import get_sensor
    from u4d_aug.metrics.extractors import Extractor, heldout_scores

    root = write_tiny_root(tmp_path / "root", num_frames=3)
    dataset = ScanDataset(root, ["00"], labeled_only=True)
    scans = [dataset[i]["points"] for i in range(3)]
    labels = [dataset[i]["labels"] for i in range(3)]
    sensor = get_sensor("hdl64")
    perfect = Extractor("frd", _HeightRule(sensor.max_range), "", sensor, 16, 128, "linear", "")
    scores = heldout_scores(perfect, scans, labels, batch_size=2)
    assert scores["scans"] == 3 and scores["pixels"] > 0
    assert scores["accuracy"] == 1.0 and scores["miou_present"] == 1.0
    assert set(scores["iou"]) == {"road", "building"}
    constant = Extractor("frd", _HeightRule(sensor.max_range, "road"), "", sensor, 16, 128, "linear", "")
    scores_c = heldout_scores(constant, scans, labels)
    road_fraction = scores_c["accuracy"]
    assert 0.0 < road_fraction < 1.0
    assert scores_c["iou"]["building"] == 0.0 and scores_c["iou"]["road"] == pytest.approx(road_fraction)
    assert scores_c["miou_present"] == pytest.approx(road_fraction / 2)
    with pytest.raises(InputError, match="as many label arrays"):
        heldout_scores(perfect, scans, labels[:1])


def test_training_records_heldout_scores(trained, tmp_path):
    """The checkpoint records the saved net's scores on the held-out scans, and a net trained a little longer on
    the tiny world (road below the sensor, walls beside it: separable by height) beats the larger class on them."""
    from u4d_aug.data.datasets import ScanDataset
    from u4d_aug.metrics.extractors import heldout_scores

    dataset = ScanDataset(trained["root"], ["00"], labeled_only=True)
    picks = [dataset[0], dataset[4]]  # train.val_scans = 2 evenly spaced of the 5
    for kind in ("frd", "fpd"):
        heldout = torch.load(trained[kind][0], weights_only=False)["heldout"]
        assert heldout["scans"] == 2 and set(heldout["iou"]) == {"road", "building"}
        again = heldout_scores(
            load_extractor(trained[kind][0]), [p["points"] for p in picks], [p["labels"] for p in picks]
        )
        assert heldout == again
    # road holds 54% of the held-out pixels: a net predicting one class scores <= 0.54 and IoU 0 on the other.
    # Before the BatchNorm statistics were recomputed after training, fpd at lr 1e-2 scored one class in eval mode
    # on 3 of 8 seeds (its training loss near 0.01: stale running statistics); with them all 8 score >= 0.99
    for kind, steps in (("frd", 30), ("fpd", 200)):
        cfg = extractor_config(trained["root"], tmp_path / kind)
        cfg.train.steps, cfg.train.lr = steps, 1e-2
        heldout = torch.load(train_extractor(kind, cfg)[0], weights_only=False)["heldout"]
        assert heldout["accuracy"] > 0.6 and min(heldout["iou"].values()) > 0.3, (kind, heldout)
    cfg = extractor_config(trained["root"], tmp_path / "o")
    cfg.data.val_sequences = ("07",)
    with pytest.raises(InputError, match="07"):  # a missing held-out split fails before any training
        train_extractor("frd", cfg)


def test_a_non_finite_loss_stops_extractor_training_without_a_checkpoint(trained, tmp_path, monkeypatch):
    from u4d_aug.metrics.extractors import RangeSegNet

    monkeypatch.setattr(RangeSegNet, "forward", lambda self, image, labels: torch.tensor(float("inf")))
    out = tmp_path / "nan"
    with pytest.raises(NonFiniteLossError, match="training step 1: the loss is inf"):
        train_extractor("frd", extractor_config(trained["root"], out))
    assert not (out / "frd.pt").exists() and not (out / ".frd.lock").exists()
    assert not out.exists()  # it held only the run's frd_config.yaml: a failed run leaves no folder it created


def test_a_bad_data_root_is_one_error_line_and_leaves_no_folder(tmp_path, capsys):
    from u4d_aug.cli import main

    out = tmp_path / "runs" / "extractor"
    missing = tmp_path / "missing"
    argv = ["train-extractor", "frd", str(TINY_CONFIG), f"data.root={missing}", f"out_dir={out}", "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {missing}")
    assert not (tmp_path / "runs").exists()
    (tmp_path / "kept").mkdir()  # a folder that was there before the run stays
    assert main([*argv[:4], f"out_dir={tmp_path / 'kept'}"]) == 2
    assert (tmp_path / "kept").is_dir()


@pytest.mark.parametrize(
    ("override", "key"),
    [("train.steps=0", "train.steps"), ("train.lr=.nan", "train.lr"), ("train.lr=-1e-3", "train.lr"),
     ("train.batch_size=0", "train.batch_size"), ("data.width=0", "data.width"), ("model.levels=0", "model.levels")],
)  # fmt: skip
def test_degenerate_numbers_are_refused_at_config_time(tmp_path, override, key):
    with pytest.raises(InputError, match=f"'{key}'"):
        load_config(ExtractorConfig, TINY_CONFIG, [override])


def test_recalibrated_batchnorm_matches_the_final_weights_in_eval_mode():
    """After `recalibrate_batchnorm` the eval-mode net gives what train mode gives on the calibration batch (up to
    the unbiased variance BatchNorm stores), where stale running statistics (those of inputs shifted by +5) did not."""
    from u4d_aug.metrics.extractors import PointNetSeg, recalibrate_batchnorm

    torch.manual_seed(0)
    net = PointNetSeg(16, 8, 8)
    batch = torch.randn(2, 300, 3)
    net.train()
    with torch.no_grad():
        for _ in range(20):
            net.logits(batch + 5.0)  # running statistics of other inputs
        train_mode = net.logits(batch)
    net.eval()
    stale = (net.logits(batch) - train_mode).abs().max()
    recalibrate_batchnorm(net, [batch])
    assert not net.training  # its mode is restored
    fresh = (net.logits(batch) - train_mode).abs().max()
    assert stale > 0.5 and fresh < 0.03, (stale, fresh)
    assert (net.logits(batch).argmax(1) == train_mode.argmax(1)).float().mean() > 0.95  # near-ties may flip
    assert all(m.momentum == 0.1 for m in net.modules() if isinstance(m, torch.nn.BatchNorm1d))
