"""Figures (u4d_aug/viz.py): the SemanticKITTI palette, PNGs written whole, shapes checked before drawing."""

from __future__ import annotations

import struct
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from u4d_aug.viz import label_colors, plot_gate_weights, plot_scan, plot_sequence, save_figure

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) in pixels from a PNG's IHDR chunk."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    return struct.unpack(">II", data[16:24])


def test_label_colors_semantickitti_palette_and_other_class_counts():
    colors = label_colors(np.array([0, 8, 19, 25]))
    np.testing.assert_allclose(colors[0], np.array([100, 150, 245]) / 255)  # car
    np.testing.assert_allclose(colors[1], np.array([255, 0, 255]) / 255)  # road
    np.testing.assert_array_equal(colors[2:], 0.0)  # the ignore id, and ids past it, are black
    tab20 = plt.get_cmap("tab20")(np.arange(20))[:, :3]
    other = label_colors(np.array([0, 4, 5]), num_classes=5)
    np.testing.assert_allclose(other[:2], tab20[[0, 4]])
    np.testing.assert_array_equal(other[2], 0.0)  # not a class of a 5-class net


def test_save_figure_writes_a_png_and_closes_the_figure(tmp_path):
    fig = plt.figure(figsize=(2, 1))
    path = save_figure(fig, tmp_path / "sub" / "f.png", dpi=50)
    assert path == tmp_path / "sub" / "f.png" and png_size(path)[0] > 0
    assert not plt.fignum_exists(fig.number)
    assert [p.name for p in path.parent.iterdir()] == ["f.png"]  # no temp file left behind


def test_plot_scan_adds_the_label_row_when_labels_are_known(tmp_path):
    rng = np.random.default_rng(0)
    points = rng.uniform(-30, 30, (200, 4)).astype(np.float32)
    depth = rng.uniform(0, 40, (8, 64))
    depth[0, :5] = 0.0  # no return: drawn black
    plain = plot_scan(tmp_path / "plain.png", points, depth, rng.uniform(0, 1, (8, 64)))
    labels = rng.integers(0, 19, 200)
    label_image = rng.integers(-1, 19, (8, 64))
    labelled = plot_scan(tmp_path / "labels.png", points, depth, rng.uniform(0, 1, (8, 64)), labels, label_image)
    assert png_size(labelled)[1] > png_size(plain)[1]


def test_plot_gate_weights_checks_lengths(tmp_path):
    path = plot_gate_weights(tmp_path / "gates.png", ["in", "mid", "out"], [0.9, 0.4, 0.8], [0.1, 0.6, 0.2])
    assert png_size(path)[0] > 0
    with pytest.raises(ValueError, match="3 names, 2 alpha_s, 3 alpha_t"):
        plot_gate_weights(tmp_path / "bad.png", ["in", "mid", "out"], [0.9, 0.4], [0.1, 0.6, 0.2])
    assert not (tmp_path / "bad.png").exists()


def test_plot_sequence_checks_lengths(tmp_path):
    with pytest.raises(ValueError, match="expected L each"):
        plot_sequence(tmp_path / "x.png", [np.ones((4, 8))], [np.zeros((3, 4))] * 2, np.tile(np.eye(4), (2, 1, 1)))
