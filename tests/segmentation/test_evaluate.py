"""mIoU and ECE of a segmentation checkpoint (segmentation/evaluate.py): the summary equals the metrics computed by
hand, the printed table, the command; an untrained tiny net is enough to score."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from segmentation.config import SegTrainConfig
from segmentation.evaluate import (
    add_seg_eval_arguments,
    evaluate,
    evenly_spaced,
    format_summary,
    run_seg_eval,
    summary_of,
)
from segmentation.metrics import CalibrationAccumulator, ConfusionMatrix, mean_iou, top_confusions
from segmentation.models import build_model
from segmentation.predict import load_checkpoint, model_from_checkpoint, predict_probs
from segmentation.train import final_weights
from tests.tiny_nets import SEG_TINY
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.labels import SEMANTICKITTI_IGNORE
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_torch_save


@pytest.fixture(scope="module")
def segmentor(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(toy root, model.pt of the untrained configs/seg/tiny.yaml net, as seg-train writes it at step 0)."""
    root = write_toy_root(tmp_path_factory.mktemp("toy"))
    cfg = load_config(SegTrainConfig, SEG_TINY, [f"data.root={root}"])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = build_model(cfg.model)
    path = tmp_path_factory.mktemp("run") / "model.pt"
    atomic_torch_save(path, final_weights(cfg, 0, model, None))
    return root, path


def test_evaluate_matches_metrics_by_hand(segmentor, tmp_path):
    root, ckpt = segmentor
    png = tmp_path / "rel.png"
    summary = evaluate(ckpt, root, ["01"], reliability_png=png)
    assert png.is_file() and summary["num_scans"] == 3 and summary["sequences"] == ["01"]

    model = model_from_checkpoint(load_checkpoint(ckpt), torch.device("cpu"))
    cm, calibration = ConfusionMatrix(19, SEMANTICKITTI_IGNORE), CalibrationAccumulator(SEMANTICKITTI_IGNORE)
    for item in ScanDataset(root, ["01"]):
        probs = predict_probs(model, item["points"], torch.device("cpu"))
        cm.update(probs.argmax(1), item["labels"])
        calibration.update(probs, item["labels"])
    assert summary["miou"] == pytest.approx(mean_iou(cm.matrix))
    assert summary["ece_per_scan"] == pytest.approx(calibration.ece_per_scan)
    assert summary["ece_pooled"] == pytest.approx(calibration.ece_pooled)
    assert summary["classes_present"] == ["car", "road", "building"]
    present = [summary["iou"][c] for c in summary["classes_present"]]
    assert summary["miou_present"] == pytest.approx(np.mean(present))
    np.testing.assert_array_equal(summary["confusion"], cm.matrix)
    assert "mIoU" in format_summary(summary)


def test_run_seg_eval_prints_table_and_json(segmentor, tmp_path, capsys):
    root, ckpt = segmentor
    parser = argparse.ArgumentParser()
    add_seg_eval_arguments(parser)
    assert run_seg_eval(parser.parse_args([str(ckpt), str(root), "--sequences", "01", "--json"])) == 0
    summary = json.loads(capsys.readouterr().out)
    assert set(summary) >= {"miou", "iou", "ece_per_scan", "ece_pooled", "bins", "miou_present"}
    png, confusion_png = tmp_path / "r.png", tmp_path / "c.png"
    # the 3 scans of sequence 01 again, so that the table shows the summary printed as json above
    args = [str(ckpt), str(root), "--sequences", "01", "--max-scans", "3", "--png", str(png)]
    args += ["--confusion-png", str(confusion_png)]
    assert run_seg_eval(parser.parse_args(args)) == 0
    text = capsys.readouterr().out
    assert "ECE per scan" in text and "road" in text and png.is_file()
    assert confusion_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # each class row names what its points are mistaken for, from the confusion matrix of the summary
    names, checked = list(summary["iou"]), 0
    for k, confused in enumerate(top_confusions(summary["confusion"])):
        if confused:
            row = next(line for line in text.splitlines() if line.startswith(names[k] + " "))
            assert f"{names[confused[0][0]]} {100 * confused[0][1]:.0f} %" in row
            checked += 1
    assert checked > 0  # the tiny net mistakes some class for another


def test_evenly_spaced():
    assert evenly_spaced(5, None) == [0, 1, 2, 3, 4]
    assert evenly_spaced(10, 3) == [0, 4, 9] or evenly_spaced(10, 3) == [0, 5, 9]
    assert evenly_spaced(3, 10) == [0, 1, 2]


@pytest.mark.real
def test_evaluate_on_real_semantickitti(segmentor, real_root):
    """Sim-to-real style: a checkpoint evaluated on real labeled scans; only GT classes enter miou_present."""
    _, ckpt = segmentor
    summary = evaluate(ckpt, real_root / "semantickitti", ["00"], max_scans=1)
    assert summary["num_scans"] == 1 and summary["num_points"] > 100_000
    assert {"road", "car", "building", "vegetation"} <= set(summary["classes_present"])
    assert 0.0 <= summary["miou_present"] <= 1.0 and not math.isnan(summary["ece_pooled"])


def hand_made_summary() -> dict:
    """Classes a, b, c; ground truth a a a c c, predicted a a b a c: b has no ground truth but a false positive."""
    cm = ConfusionMatrix(3, 3)
    cm.update_matrix(np.array([[2, 1, 0], [0, 0, 0], [1, 0, 1]]))  # rows ground truth, columns prediction
    return summary_of(cm, CalibrationAccumulator(3), ["a", "b", "c"])


def test_summary_adds_the_miou_over_the_classes_with_ground_truth():
    summary = hand_made_summary()
    assert summary["iou"] == {"a": 0.5, "b": 0.0, "c": 0.5}  # a: 2 / (2 + 1 + 1), b: 0 / 1, c: 1 / (1 + 1)
    assert summary["miou"] == pytest.approx(1 / 3) and summary["miou_present"] == 0.5
    assert summary["classes_present"] == ["a", "c"] and summary["num_points"] == 5


def test_table_names_what_each_class_is_mistaken_for_and_the_range_bands():
    summary = hand_made_summary()
    summary["bands"] = [{"range": [0, 20], "miou": 0.25, "points": 4}, {"range": [20, None], "miou": None, "points": 0}]
    rows = format_summary(summary).splitlines()
    assert rows[1:4] == ["a   50.00  b 33 %", "b    0.00   (no ground truth)", "c   50.00  a 50 %"]
    assert "mIoU (classes with ground truth)     50.00 %" in rows and "scans 0, points 5" in rows
    assert "ECE per scan (Calib3D, mean)           n/a %" in rows
    assert rows[-2:] == [
        "mIoU at 0-20 m                       25.00 %  (4 points)",
        "mIoU at >= 20 m                        n/a %  (0 points)",
    ]


def test_the_command_refuses_a_scan_count_below_one(segmentor):
    parser = argparse.ArgumentParser()
    add_seg_eval_arguments(parser)
    root, ckpt = segmentor
    with pytest.raises(InputError, match="--max-scans must be >= 1, got 0"):
        run_seg_eval(parser.parse_args([str(ckpt), str(root), "--max-scans", "0"]))
