"""PNG figures for the segmentation reports: reliability diagram (Guo et al. 2017), confusion matrix, learning
curves, paired seeds.

Figures are built with `matplotlib.figure.Figure` (Agg canvas, no pyplot global state) and written atomically.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from segmentation.metrics import ReliabilityBins, confusion_shares
from u4d_aug.io import atomic_open

X_KEYS = ("step", "iteration", "iter", "epoch")
# bookkeeping keys left out of the default curves (other scales than losses and metrics)
NOT_CURVES = frozenset(X_KEYS) | {
    "lr",
    "time",
    "elapsed",
    "wall_time",
    "seconds",
    "rank",
    "seed",
    "world_size",
}


def _save(fig: Figure, path: str | os.PathLike) -> None:
    FigureCanvasAgg(fig)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=120)


def plot_reliability(bins: ReliabilityBins, path: str | os.PathLike, title: str = "") -> None:
    """Reliability diagram: accuracy per confidence bin against the diagonal, gaps shaded, counts below."""
    edges = bins.edges
    centres, width = (edges[:-1] + edges[1:]) / 2, edges[1] - edges[0]
    accuracy, confidence = np.nan_to_num(bins.accuracy), np.nan_to_num(bins.confidence)
    filled = bins.count > 0

    fig = Figure(figsize=(4.5, 5.5))
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    top.bar(centres[filled], accuracy[filled], width=width, edgecolor="black", color="tab:blue", label="accuracy")
    top.bar(
        centres[filled],
        (confidence - accuracy)[filled],
        bottom=accuracy[filled],
        width=width,
        edgecolor="tab:red",
        color="tab:red",
        alpha=0.3,
        label="gap to confidence",
    )
    top.plot([0, 1], [0, 1], "k--", linewidth=1, label="perfect calibration")
    top.set_xlim(0, 1)
    top.set_ylim(0, 1)
    top.set_ylabel("accuracy")
    ece = bins.ece
    ece_text = "n/a" if math.isnan(ece) else f"{100 * ece:.2f}%"
    top.set_title(f"{title}\npooled ECE {ece_text}" if title else f"pooled ECE {ece_text}", fontsize=10)
    top.legend(loc="upper left", fontsize=8)
    bottom.bar(centres, bins.count / max(bins.total, 1), width=width, edgecolor="black", color="tab:gray")
    bottom.set_xlabel("confidence")
    bottom.set_ylabel("fraction")
    fig.tight_layout()
    _save(fig, path)


def plot_confusion(matrix: np.ndarray, class_names: Sequence[str], path: str | os.PathLike, title: str = "") -> None:
    """Row-normalised confusion matrix (share of each ground-truth class per predicted class, %), cells >= 1 %
    written in; rows without ground truth left blank."""
    shares = confusion_shares(matrix)  # (K, K)
    present = np.asarray(matrix).sum(axis=1) > 0
    k = len(class_names)
    fig = Figure(figsize=(1.6 + 0.42 * k, 1.2 + 0.38 * k))
    ax = fig.subplots()
    image = ax.imshow(np.where(present[:, None], 100 * shares, np.nan), cmap="Blues", vmin=0, vmax=100)
    for r, c in zip(*np.nonzero(shares >= 0.01)):
        color = "white" if shares[r, c] > 0.6 else "black"
        ax.text(c, r, f"{100 * shares[r, c]:.0f}", ha="center", va="center", fontsize=6, color=color)
    ax.set_xticks(range(k), class_names, rotation=90, fontsize=7)
    ax.set_yticks(range(k), class_names, fontsize=7)
    ax.set_xlabel("predicted")
    ax.set_ylabel("ground truth")
    fig.colorbar(image, ax=ax, fraction=0.04, label="% of the ground-truth points")
    ax.set_title(title or "confusion (rows sum to 100 %)", fontsize=9)
    fig.tight_layout()
    _save(fig, path)


def plot_learning_curve(
    records: Iterable[dict],
    path: str | os.PathLike,
    x_key: str | None = None,
    keys: Sequence[str] | None = None,
) -> None:
    """Learning curves from jsonl log records: keys containing "loss" on the left panel, other metrics right.

    `x_key` defaults to the first of step / iteration / iter / epoch present; `keys` defaults to every numeric
    key except bookkeeping ones (`NOT_CURVES`: lr, time, ...); records without a key are skipped for that
    curve (e.g. eval metrics logged less often).
    """
    records = list(records)
    if x_key is None:
        x_key = next((k for k in X_KEYS if any(k in r for r in records)), None)
    if keys is None:
        keys = sorted(
            {
                k
                for r in records
                for k, v in r.items()
                if k != x_key and k not in NOT_CURVES and isinstance(v, int | float) and not isinstance(v, bool)
            }
        )
    series: dict[str, tuple[list[float], list[float]]] = {}
    for key in keys:
        xs, ys = [], []
        for i, r in enumerate(records):
            v = r.get(key)
            if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
                xs.append(float(r.get(x_key, i)) if x_key else float(i))
                ys.append(float(v))
        if xs:
            series[key] = (xs, ys)

    fig = Figure(figsize=(10, 4))
    left, right = fig.subplots(1, 2)
    for ax, group, ylabel in (
        (left, [k for k in series if "loss" in k], "loss"),
        (right, [k for k in series if "loss" not in k], "metric"),
    ):
        for key in group:
            xs, ys = series[key]
            ax.plot(xs, ys, marker="o" if len(xs) < 30 else None, markersize=3, label=key)
        ax.set_xlabel(x_key or "record")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if group:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    _save(fig, path)


def plot_arm_curves(curves: dict[str, dict[str, list[list[tuple[float, float]]]]], path: str | os.PathLike) -> None:
    """Learning curves of an experiment's arms: per arm the training loss (left) and held-out mIoU (right) against
    step, the mean over its seeds (steps every seed logged) as a line, each seed faintly.

    curves: arm -> {"loss": [per seed [(step, value), ...]], "val_miou": [...]}.
    """
    fig = Figure(figsize=(11, 4))
    axes = dict(zip(("loss", "val_miou"), fig.subplots(1, 2)))
    colors = [f"C{i}" for i in range(10)]
    for index, (arm, series) in enumerate(curves.items()):
        color = colors[index % len(colors)]
        for key, ax in axes.items():
            seeds = [dict(points) for points in series.get(key, []) if points]
            if not seeds:
                continue
            for points in seeds:
                ax.plot(list(points), list(points.values()), color=color, alpha=0.2, linewidth=0.8)
            steps = sorted(set.intersection(*(set(points) for points in seeds)))
            if steps:
                mean = [float(np.mean([points[x] for points in seeds])) for x in steps]
                marker = "o" if len(steps) < 30 else None
                ax.plot(steps, mean, color=color, marker=marker, markersize=3, label=f"{arm} ({len(seeds)})")
    for key, ax in axes.items():
        ax.set_xlabel("step")
        ax.set_ylabel("training loss" if key == "loss" else "held-out mIoU")
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    _save(fig, path)


def plot_paired(
    paired: dict[str, dict], path: str | os.PathLike, reference: str, metrics: Sequence[str] = ("miou", "ece_per_scan")
) -> None:
    """Arm - reference per seed (points), one panel per metric: a dot per seed (labelled), mean ± std bar, zero line.

    `paired[arm][metric]` is `segmentation.experiment.paired_differences` output (seeds, per_seed, mean, std, p).
    """
    arms = list(paired)
    fig = Figure(figsize=(3.6 * len(metrics), 1.0 + 0.85 * max(len(arms), 1)))
    axes = np.atleast_1d(fig.subplots(1, len(metrics), sharey=True))
    for ax, metric in zip(axes, metrics):
        for row, arm in enumerate(arms):
            stat = paired[arm][metric]
            diffs = 100 * np.asarray(stat["per_seed"], dtype=np.float64)
            ax.scatter(diffs, np.full(len(diffs), row), color="tab:blue", s=18, zorder=3)
            for seed, d in zip(stat["seeds"], diffs):
                ax.annotate(str(seed), (d, row), textcoords="offset points", xytext=(0, -9), ha="center", fontsize=6)
            if stat["mean"] is not None:
                mean, std = 100 * stat["mean"], 100 * stat["std"]
                ax.errorbar(mean, row - 0.3, xerr=std, fmt="D", color="black", markersize=4, capsize=3)
                p_text = "" if stat.get("p") is None else f", p {stat['p']:.2g}"
                ax.annotate(f"{mean:+.2f}{p_text}", (mean, row - 0.3), textcoords="offset points", xytext=(0, 5),
                            ha="center", fontsize=7)  # fmt: skip
        ax.axvline(0.0, color="tab:red", linewidth=1)
        ax.set_xlabel(f"{metric} - {reference} (points)")
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(range(len(arms)), arms)
    axes[0].set_ylim(len(arms) - 0.4, -0.85)
    fig.suptitle(f"paired by seed against {reference}: dots = seeds, diamond = mean ± std", fontsize=9)
    fig.tight_layout()
    _save(fig, path)
