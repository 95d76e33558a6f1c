"""PNG figures of the segmentation reports (segmentation/plots.py): written whole, and what each panel draws."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from segmentation import plots
from segmentation.metrics import CalibrationAccumulator, ReliabilityBins
from segmentation.plots import plot_arm_curves, plot_confusion, plot_learning_curve, plot_paired, plot_reliability

SCAN1_PROBS = [[0.95, 0.05], [0.85, 0.15], [0.35, 0.65], [0.45, 0.55]]
SCAN1_TARGET = [0, 1, 1, 0]  # correct, wrong, correct, wrong


@pytest.fixture
def drawn(monkeypatch) -> list[Figure]:
    """The figures the plot functions would write, kept instead of written."""
    figures: list[Figure] = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figures.append(fig))
    return figures


def curves_of(ax) -> dict[str, tuple[list[float], list[float]]]:
    """label -> (x, y) of the labelled lines of an axes."""
    return {
        line.get_label(): (list(line.get_xdata()), list(line.get_ydata()))
        for line in ax.get_lines()
        if not line.get_label().startswith("_")
    }


def _is_png(path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plots_write_png_atomically(tmp_path, monkeypatch):
    acc = CalibrationAccumulator(2)
    acc.update(np.array(SCAN1_PROBS), SCAN1_TARGET)
    plot_reliability(acc.pooled, tmp_path / "rel.png", title="toy")
    plot_reliability(ReliabilityBins.empty(), tmp_path / "empty.png")
    records = [{"step": s, "loss": 1 / (s + 1), "lr": 1e-3} for s in range(0, 50, 5)]
    records += [{"step": 25, "miou": 0.4, "ece_pooled": 0.05}, {"step": 50, "miou": 0.5}]
    plot_learning_curve(records, tmp_path / "sub" / "curve.png")
    plot_learning_curve([], tmp_path / "none.png")
    plot_confusion(np.array([[5, 1, 0], [2, 7, 0], [0, 0, 0]]), ["a", "b", "c"], tmp_path / "confusion.png")
    for name in ("rel.png", "empty.png", "sub/curve.png", "none.png", "confusion.png"):
        assert _is_png(tmp_path / name)
    leftovers = [p.name for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    assert leftovers == []

    def killed_midway(fig, file, **kwargs):  # the PNG encoder dies after its first bytes
        file.write(b"\x89PNG\r\n\x1a\n half")
        raise MemoryError("killed midway")

    old = (tmp_path / "rel.png").read_bytes()
    monkeypatch.setattr(Figure, "savefig", killed_midway)
    with pytest.raises(MemoryError):
        plot_reliability(acc.pooled, tmp_path / "rel.png", title="toy")
    assert (tmp_path / "rel.png").read_bytes() == old  # the previous figure, whole
    assert [p.name for p in tmp_path.rglob("*") if p.name.endswith(".tmp")] == []


def test_learning_curve_puts_losses_left_metrics_right_and_leaves_out_bookkeeping(drawn):
    records = [{"step": 0, "loss": 2.0, "lr": 1e-3}, {"step": 5, "loss": 1.0, "loss_ce": float("nan"), "time": 3.0}]
    records += [{"step": 5, "miou": 0.4, "ok": True}, {"epoch": 1}]
    plot_learning_curve(records, "unused.png")
    left, right = drawn[0].axes[:2]
    assert curves_of(left) == {"loss": ([0.0, 5.0], [2.0, 1.0])}  # the NaN loss_ce point is skipped, and lr
    assert curves_of(right) == {"miou": ([5.0], [0.4])}  # booleans and epoch are not curves
    assert left.get_xlabel() == "step"
    plot_learning_curve(records, "unused.png", x_key="epoch", keys=["miou"])
    assert curves_of(drawn[1].axes[1]) == {"miou": ([2.0], [0.4])}  # a record without the x key: its index


def test_arm_curves_draw_each_seed_and_the_mean_over_the_steps_every_seed_logged(drawn):
    seeds = [[(0, 1.0), (10, 0.5)], [(0, 3.0), (10, 1.5), (20, 1.0)]]
    plot_arm_curves({"mt": {"loss": seeds, "val_miou": []}, "empty": {"loss": [[]]}}, "unused.png")
    loss, miou = drawn[0].axes[:2]
    assert curves_of(loss) == {"mt (2)": ([0, 10], [2.0, 1.0])}
    assert len(loss.get_lines()) == 3  # two faint seed lines and the mean
    assert not miou.get_lines() and miou.texts[0].get_text() == "no data"


def test_paired_differences_are_drawn_in_points(drawn):
    paired = {
        "mt+u4d": {
            "miou": {"seeds": [0, 1], "per_seed": [0.01, 0.03], "mean": 0.02, "std": 0.01, "p": 0.2},
            "ece_per_scan": {"seeds": [0, 1], "per_seed": [-0.02, 0.0], "mean": None, "std": None},
        }
    }
    plot_paired(paired, "unused.png", reference="mt")
    miou, ece = drawn[0].axes[:2]
    np.testing.assert_allclose(miou.collections[0].get_offsets()[:, 0], [1.0, 3.0])
    np.testing.assert_allclose(ece.collections[0].get_offsets()[:, 0], [-2.0, 0.0])
    assert [t.get_text() for t in miou.texts] == ["0", "1", "+2.00, p 0.2"]
    assert [t.get_text() for t in ece.texts] == ["0", "1"]  # no mean without one
    assert miou.get_xlabel() == "miou - mt (points)"
