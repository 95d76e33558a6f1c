"""Figures (u4d_aug/viz.py): the SemanticKITTI palette, PNGs written whole, shapes checked before drawing, and
every panel explained: colour bars with units, class legends, BEV axes in metres, all-ignore labels in grey."""

from __future__ import annotations

import struct
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from u4d_aug.viz import (
    IGNORE_GREY,
    class_legend,
    class_names,
    draw_bev,
    draw_range_image,
    label_colors,
    plot_gate_weights,
    plot_scan,
    plot_sequence,
    save_figure,
    semantic_colors,
)

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


@pytest.fixture
def drawn(monkeypatch):
    """The figures the plot_* functions would save, kept open for inspection (closed after the test)."""
    figures: list[plt.Figure] = []

    def keep(fig, path, dpi=110):
        figures.append(fig)
        return Path(path)

    monkeypatch.setattr("u4d_aug.viz.save_figure", keep)
    yield figures
    for fig in figures:
        plt.close(fig)


def colorbar_labels(ax: plt.Axes) -> list[str]:
    """Labels of the colour bars drawn beside `ax` (inset axes)."""
    return [child.get_ylabel() for child in ax.child_axes]


def legend_texts(ax: plt.Axes) -> list[str]:
    legend = ax.get_legend()
    return [] if legend is None else [text.get_text() for text in legend.get_texts()]


def test_class_names_and_ignore_grey():
    assert class_names(19)[12] == "building" and len(class_names(19)) == 19
    assert class_names(16)[0] == "barrier" and class_names(3) == ("class 0", "class 1", "class 2")
    colors, labelled = semantic_colors(np.array([8, 19, 255, -1]))
    np.testing.assert_allclose(colors[0], np.array([255, 0, 255]) / 255)  # road keeps its colour
    np.testing.assert_allclose(colors[1:], np.tile(IGNORE_GREY, (3, 1)))  # ignore and unknown ids: grey
    assert labelled and not semantic_colors(np.full(5, 19))[1]


def test_range_image_colour_bar_carries_the_unit_and_the_image_height():
    fig, ax = plt.subplots(figsize=(8, 2))
    draw_range_image(ax, np.random.default_rng(0).uniform(0, 50, (8, 128)), "depth", vmin=0, vmax=50, unit="depth [m]")
    fig.canvas.draw()
    assert colorbar_labels(ax) == ["depth [m]"]
    bar = ax.child_axes[0].get_position()
    image = ax.get_position()  # after the fixed aspect shrank the axes
    assert bar.height == pytest.approx(image.height, rel=1e-3) and bar.y0 == pytest.approx(image.y0, abs=1e-3)
    assert image.x1 < bar.x0 < image.x1 + 0.05  # just right of the image, not overlapping it
    draw_range_image(ax2 := fig.add_subplot(2, 1, 2), np.ones((4, 8)), "no unit")
    assert colorbar_labels(ax2) == []  # callers without a unit get the old picture
    plt.close(fig)


def test_bev_axes_in_metres_with_a_height_colour_bar_only_when_coloured_by_height():
    points = np.array([[1.0, 2.0, -1.0], [-10.0, 5.0, 0.5], [80.0, 0.0, 0.0]])  # the last one outside +-50 m
    fig, (by_height, by_colour) = plt.subplots(1, 2)
    handle = draw_bev(by_height, points, title="BEV")
    assert len(handle.get_offsets()) == 2
    draw_bev(by_colour, points, np.zeros((3, 3)), extent=20.0)
    for ax in (by_height, by_colour):
        assert "[m]" in ax.get_xlabel() and "[m]" in ax.get_ylabel() and ax.get_aspect() == 1.0
    assert colorbar_labels(by_height) == ["height z [m]"] and colorbar_labels(by_colour) == []
    assert by_colour.get_xlim() == (-20.0, 20.0)
    plt.close(fig)


def test_class_legend_names_the_classes_present_in_id_order():
    fig, ax = plt.subplots()
    legend = class_legend(ax, np.array([12, 0, 0, 19, 8, 255]))
    assert legend_texts(ax) == ["car", "road", "building", "ignore"]
    np.testing.assert_allclose(legend.legend_handles[1].get_facecolor()[:3], np.array([255, 0, 255]) / 255)
    assert class_legend(ax, np.full(4, 19)) is None  # nothing but ignore: no legend, the title says so
    plt.close(fig)


def test_plot_scan_explains_every_panel(tmp_path, drawn):
    rng = np.random.default_rng(0)
    points = rng.uniform(-30, 30, (200, 4)).astype(np.float32)
    labels = np.where(np.arange(200) < 100, 8, 14)  # road and vegetation
    label_image = rng.choice([-1, 8, 14, 19], (8, 64))
    plot_scan(tmp_path / "s.png", points, rng.uniform(0, 40, (8, 64)), rng.uniform(0, 1, (8, 64)), labels, label_image)
    depth, intensity, classes, bev = drawn[0].axes[:4]
    assert colorbar_labels(depth) == ["depth [m]"] and colorbar_labels(intensity) == ["intensity [0, 1]"]
    assert classes.get_title() == "semantic class (grey: ignore)"
    assert legend_texts(bev) == ["road", "vegetation"] and "[m]" in bev.get_xlabel()
    assert "coloured by semantic class" in bev.get_title()


def test_all_ignore_labels_draw_grey_points_and_say_no_labels(tmp_path, drawn):
    rng = np.random.default_rng(1)
    points = rng.uniform(-30, 30, (50, 4)).astype(np.float32)
    label_image = np.where(rng.uniform(size=(8, 64)) < 0.3, -1, 19)  # returns all ignore, the rest empty
    plot_scan(tmp_path / "s.png", points, rng.uniform(1, 40, (8, 64)), rng.uniform(0, 1, (8, 64)),
              np.full(50, 19), label_image)  # fmt: skip
    classes, bev = drawn[0].axes[2:4]
    assert "no labels" in classes.get_title() and "no labels" in bev.get_title()
    np.testing.assert_allclose(bev.collections[0].get_facecolors()[:, :3], np.tile(IGNORE_GREY, (50, 1)))
    pixels = classes.images[0].get_array()
    np.testing.assert_allclose(pixels[label_image == 19], np.tile(IGNORE_GREY, ((label_image == 19).sum(), 1)))
    np.testing.assert_array_equal(pixels[label_image == -1], 0.0)  # no return stays black
    assert bev.get_legend() is None


def test_plot_scan_without_labels_colours_the_bev_by_height(tmp_path, drawn):
    rng = np.random.default_rng(2)
    depth = np.zeros((8, 64))  # not one return: the colour scale still has a range
    plot_scan(tmp_path / "s.png", rng.uniform(-9, 9, (30, 4)), depth, np.zeros((8, 64)))
    bev = drawn[0].axes[2]
    assert bev.get_title() == "BEV, coloured by height" and colorbar_labels(bev) == ["height z [m]"]


def test_plot_sequence_has_depth_bars_and_a_frame_legend(tmp_path, drawn):
    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    plot_sequence(tmp_path / "q.png", [rng.uniform(0, 30, (4, 32))] * 3, [rng.uniform(-5, 5, (20, 4))] * 3, poses)
    *frames, bev = drawn[0].axes[:4]
    assert [colorbar_labels(ax) for ax in frames] == [["depth [m]"]] * 3
    assert legend_texts(bev) == ["frame 0", "frame 1", "frame 2", "sensor path"]
    assert bev.get_xlabel() == "x [m] (forward)" and bev.get_aspect() == 1.0
