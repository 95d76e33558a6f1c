"""Pictures a person would rather look at than read: range images, BEV, uncertainty maps (matplotlib, Agg).

Every colour says what it means: range-image panels carry a colour bar labelled with their quantity and unit,
panels coloured by semantic class a legend of the classes shown, BEVs axes in metres at equal aspect.
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.artist import Artist  # noqa: E402
from matplotlib.colorbar import Colorbar  # noqa: E402
from matplotlib.legend import Legend  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from u4d_aug.data.labels import NUSCENES_CLASSES, SEMANTICKITTI_CLASSES  # noqa: E402
from u4d_aug.io import atomic_write_bytes  # noqa: E402

# SemanticKITTI train-id colours (RGB 0-255) in train-id order 0..18, from semantic-kitti.yaml's colour map;
# index 19 (ignore) is black.
SEMANTICKITTI_COLORS = (
    np.array(
        [
            [100, 150, 245],  # car
            [100, 230, 245],  # bicycle
            [30, 60, 150],  # motorcycle
            [80, 30, 180],  # truck
            [0, 0, 255],  # other-vehicle
            [255, 30, 30],  # person
            [255, 40, 200],  # bicyclist
            [150, 30, 90],  # motorcyclist
            [255, 0, 255],  # road
            [255, 150, 255],  # parking
            [75, 0, 75],  # sidewalk
            [175, 0, 75],  # other-ground
            [255, 200, 0],  # building
            [255, 120, 50],  # fence
            [0, 175, 0],  # vegetation
            [135, 60, 0],  # trunk
            [150, 240, 80],  # terrain
            [255, 240, 150],  # pole
            [255, 0, 0],  # traffic-sign
            [0, 0, 0],  # ignore
        ],
        dtype=np.float32,
    )
    / 255.0
)
# ignored points and pixels in class-coloured panels: a neutral grey, seen on the black background
IGNORE_GREY = np.array([0.6, 0.6, 0.6], dtype=np.float32)
# colour-bar labels: the quantity each panel shows and its unit
DEPTH_LABEL = "depth [m]"
INTENSITY_LABEL = "intensity [0, 1]"
ENTROPY_LABEL = "H(p) [nats]"
HEIGHT_LABEL = "height z [m]"
BEV_X_LABEL, BEV_Y_LABEL = "x [m] (forward)", "y [m] (left)"
HEIGHT_RANGE = (-3.0, 3.0)  # metres of z the BEV's height colours span


def label_colors(labels: np.ndarray, num_classes: int = 19) -> np.ndarray:
    """(N,) train ids -> (N, 3) RGB in [0, 1]; SemanticKITTI palette for 19 classes, tab20 otherwise."""
    labels = np.asarray(labels)
    if num_classes == 19:
        return SEMANTICKITTI_COLORS[np.clip(labels, 0, 19)]
    palette = plt.get_cmap("tab20")(np.arange(20))[:, :3]
    colors = palette[np.clip(labels, 0, 19) % 20]
    colors[labels >= num_classes] = 0.0
    return colors


def class_names(num_classes: int = 19) -> tuple[str, ...]:
    """Names of train ids 0..K-1: SemanticKITTI's for K = 19, nuScenes' for K = 16, else "class k"."""
    if num_classes == len(SEMANTICKITTI_CLASSES):
        return SEMANTICKITTI_CLASSES
    if num_classes == len(NUSCENES_CLASSES):
        return NUSCENES_CLASSES
    return tuple(f"class {k}" for k in range(num_classes))


def semantic_colors(labels: np.ndarray, num_classes: int = 19) -> tuple[np.ndarray, bool]:
    """(...) train ids -> (..., 3) RGB with every id outside 0..K-1 (ignore) grey, and whether any id is a class."""
    labels = np.asarray(labels)
    known = (labels >= 0) & (labels < num_classes)
    colors = label_colors(np.where(known, labels, num_classes), num_classes).astype(np.float32)
    colors[~known] = IGNORE_GREY
    return colors, bool(known.any())


def add_colorbar(ax: plt.Axes, handle, label: str, width: float = 0.02) -> Colorbar:
    """Colour bar right of `ax`, as tall as it, labelled "quantity [unit]"; an inset, so it follows a shrunk aspect."""
    cax = ax.inset_axes((1.0 + max(width, 0.006), 0.0, width, 1.0))
    bar = ax.figure.colorbar(handle, cax=cax)
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return bar


def class_legend(ax: plt.Axes, labels: np.ndarray, num_classes: int = 19) -> Legend | None:
    """Legend right of `ax` naming each class in `labels` (train ids) in its colour, ignore last; None if none."""
    labels = np.asarray(labels).ravel()
    present = np.unique(labels[labels >= 0])
    names = class_names(num_classes)
    handles = [Patch(color=tuple(label_colors(np.array([k]), num_classes)[0]), label=names[k]) for k in present
               if k < num_classes]  # fmt: skip
    if not handles:
        return None
    if (present >= num_classes).any():
        handles.append(Patch(color=tuple(IGNORE_GREY), label="ignore"))
    return ax.legend(handles=handles, title="semantic class", loc="upper left", bbox_to_anchor=(1.02, 1.0),
                     fontsize=7, title_fontsize=8, frameon=False, borderaxespad=0.0)  # fmt: skip


def save_figure(fig: plt.Figure, path: str | Path, dpi: int = 110) -> Path:
    """Render a figure to PNG bytes and write them atomically; closes the figure."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    return Path(path)


def top_margin(fig: plt.Figure, inches: float = 0.75) -> float:
    """Gridspec `top` leaving `inches` above the panels for the figure's title (matplotlib's 0.88 leaves more)."""
    return 1.0 - inches / fig.get_figheight()


def range_aspect(shape: tuple[int, ...]) -> float:
    """imshow aspect of an (H, W) range image: wide images squashed (W/H/8) to stay readable."""
    return max(shape[1] / shape[0] / 8, 1)


def draw_range_image(
    ax: plt.Axes, image: np.ndarray, title: str, cmap: str = "turbo", vmin=None, vmax=None, unit: str | None = None
):
    """One (H, W) channel; NaN pixels (no return) drawn black; `unit` (e.g. "depth [m]") adds a colour bar."""
    cm = plt.get_cmap(cmap).with_extremes(bad="black")
    handle = ax.imshow(image, cmap=cm, vmin=vmin, vmax=vmax, interpolation="nearest", aspect=range_aspect(image.shape))
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    if unit is not None:
        add_colorbar(ax, handle, unit, width=0.012)
    return handle


def draw_label_image(ax: plt.Axes, label_image: np.ndarray, num_classes: int = 19, title: str = "semantic class"):
    """(H, W) train ids, -1 = no return (black), ignore grey; the title says "no labels" when every id is ignore."""
    rgb, labelled = semantic_colors(label_image, num_classes)
    rgb[label_image < 0] = 0.0
    handle = ax.imshow(rgb, interpolation="nearest", aspect=range_aspect(label_image.shape))
    if not labelled:
        title = f"{title}: no labels (every point ignore, grey)"
    elif (label_image >= num_classes).any():
        title = f"{title} (grey: ignore)"
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    return handle


def draw_bev(
    ax: plt.Axes,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    extent: float = 50.0,
    title: str = "BEV",
    point_size: float = 0.2,
    *,
    height_colorbar: bool = True,
):
    """BEV scatter of (N, >=3) points within +-extent, axes in metres at equal aspect; colours given, or height z."""
    points = np.asarray(points)
    inside = (np.abs(points[:, 0]) < extent) & (np.abs(points[:, 1]) < extent)
    pts = points[inside]
    if colors is None:
        handle = ax.scatter(pts[:, 0], pts[:, 1], c=pts[:, 2], cmap="viridis", vmin=HEIGHT_RANGE[0],
                            vmax=HEIGHT_RANGE[1], s=point_size, linewidths=0, rasterized=True)  # fmt: skip
    else:
        c = np.asarray(colors)[inside]
        handle = ax.scatter(pts[:, 0], pts[:, 1], c=c, s=point_size, linewidths=0, rasterized=True)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    ax.set_facecolor("black")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(BEV_X_LABEL, fontsize=8)
    ax.set_ylabel(BEV_Y_LABEL, fontsize=8)
    ax.tick_params(labelsize=7)
    if colors is None and height_colorbar:
        add_colorbar(ax, handle, HEIGHT_LABEL, width=0.03)
    return handle


def draw_semantic_bev(
    ax: plt.Axes,
    points: np.ndarray,
    labels: np.ndarray,
    num_classes: int = 19,
    legend: bool = True,
    title: str = "BEV",
    extent: float = 50.0,
    point_size: float = 0.2,
) -> None:
    """BEV by semantic class with a legend of its classes (if `legend`); all-ignore labels: grey, "no labels"."""
    colors, labelled = semantic_colors(labels, num_classes)
    title = f"{title}, coloured by semantic class" if labelled else f"{title}: no labels (every point ignore, grey)"
    draw_bev(ax, points, colors, extent, title, point_size)
    if legend:
        class_legend(ax, labels, num_classes)


def plot_scan(
    path: str | Path,
    points: np.ndarray,
    depth_image: np.ndarray,
    reflectance_image: np.ndarray,
    labels: np.ndarray | None = None,
    label_image: np.ndarray | None = None,
    title: str = "",
    num_classes: int = 19,
) -> Path:
    """Range image (depth, intensity, labels when known) above a BEV coloured by label (legend) or height."""
    rows = 3 if label_image is not None else 2
    fig = plt.figure(figsize=(12, 1.5 * rows + 6.5))
    grid = fig.add_gridspec(rows + 1, 1, height_ratios=[1.5] * rows + [6.5], hspace=0.25, top=top_margin(fig))
    returned = depth_image > 0
    depth = np.where(returned, depth_image, np.nan)
    top = float(np.nanpercentile(depth, 99)) if returned.any() else 1.0
    draw_range_image(fig.add_subplot(grid[0]), depth, "depth (black: no return)", vmin=0, vmax=top, unit=DEPTH_LABEL)
    intensity = np.where(returned, reflectance_image, np.nan)
    draw_range_image(fig.add_subplot(grid[1]), intensity, "intensity (remission, unitless)", cmap="gray", vmin=0,
                     vmax=1, unit=INTENSITY_LABEL)  # fmt: skip
    if label_image is not None:
        label_ax = fig.add_subplot(grid[2])
        draw_label_image(label_ax, label_image, num_classes)
        if labels is None:
            class_legend(label_ax, label_image, num_classes)
    bev_ax = fig.add_subplot(grid[rows])
    if labels is not None:
        draw_semantic_bev(bev_ax, points, labels, num_classes, title="BEV")
    else:
        draw_bev(bev_ax, points, title="BEV, coloured by height")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def plot_gate_weights(
    path: str | Path, names: list[str], alpha_s: np.ndarray, alpha_t: np.ndarray, title: str = ""
) -> Path:
    """Bar chart of the MoST gates (α^s, α^t) per block, input -> output (U4D MoST figure: spatial at the ends)."""
    alpha_s, alpha_t = np.asarray(alpha_s, dtype=float), np.asarray(alpha_t, dtype=float)
    if not len(names) == len(alpha_s) == len(alpha_t):
        raise ValueError(f"plot_gate_weights: {len(names)} names, {len(alpha_s)} alpha_s, {len(alpha_t)} alpha_t")
    depth = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(4.0, 0.7 * len(names) + 1.5), 3.0))
    ax.bar(depth - 0.2, alpha_s, width=0.4, label=r"$\alpha^s$ (spatial)", color="tab:blue")
    ax.bar(depth + 0.2, alpha_t, width=0.4, label=r"$\alpha^t$ (temporal)", color="tab:orange")
    ax.axhline(0.5, color="gray", linewidth=0.8, linestyle="--")
    ax.set_xticks(depth, names)
    ax.set_ylim(0.0, 1.0)
    ax.set_xlabel("MoST block (input -> output)")
    ax.set_ylabel("mean gate weight")
    ax.set_title(title or "MoST gate weights", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    return save_figure(fig, path)


def frame_legend(ax: plt.Axes, palette: np.ndarray) -> Legend:
    """Legend inside a sequence BEV (on its black): one colour per frame, the white line the sensor's path."""
    handles: list[Artist] = [Patch(color=tuple(color), label=f"frame {i}") for i, color in enumerate(palette)]
    handles.append(Line2D([], [], color="white", marker="o", markersize=3, label="sensor path"))
    return ax.legend(handles=handles, loc="upper right", fontsize=7, facecolor="black", edgecolor="gray",
                     labelcolor="white", framealpha=0.8)  # fmt: skip


def plot_sequence(
    path: str | Path, depth_images: list[np.ndarray], clouds: list[np.ndarray], poses: np.ndarray, title: str = ""
) -> Path:
    """An L-frame sequence: each frame's depth image, beside a BEV of every frame moved into frame 0 by its pose.

    `clouds` (N_i, >=3) in their own sensor frames, `poses` (L, 4, 4) sensor-to-world (TTCE/CTC's T_i): coloured by
    frame, static structure overlaps where the frames follow their poses and shows L copies where they do not; the
    sensor positions T_0^-1 T_i are the white path.
    """
    poses = np.asarray(poses, dtype=np.float64)
    frames = len(clouds)
    if not frames or len(depth_images) != frames or poses.shape != (frames, 4, 4):
        raise ValueError(
            f"plot_sequence: {len(depth_images)} depth images, {frames} clouds, poses {poses.shape}; expected L each"
        )
    relative = np.linalg.solve(poses[0], poses)  # (L, 4, 4) frame i -> frame 0
    palette = plt.get_cmap("tab10")(np.arange(frames) % 10)[:, :3]
    fig = plt.figure(figsize=(19, max(1.6 * frames, 7.0)))
    grid = fig.add_gridspec(frames, 2, width_ratios=[12, 6.5], wspace=0.12, hspace=0.4, top=top_margin(fig))
    finite = np.concatenate([d[d > 0].ravel() for d in depth_images] + [np.ones(1)])
    top = float(np.percentile(finite, 99))
    for i, depth in enumerate(depth_images):
        ax = fig.add_subplot(grid[i, 0])
        image = np.where(depth > 0, depth, np.nan)
        draw_range_image(ax, image, f"frame {i}: depth (black: no return)", vmin=0, vmax=top, unit=DEPTH_LABEL)
        ax.title.set_color(palette[i])
    moved = [np.asarray(c)[:, :3] @ relative[i, :3, :3].T + relative[i, :3, 3] for i, c in enumerate(clouds)]
    colors = np.concatenate([np.tile(palette[i], (len(m), 1)) for i, m in enumerate(moved)])
    order = np.random.default_rng(0).permutation(len(colors))  # frames interleaved, so no frame hides the others
    bev = fig.add_subplot(grid[:, 1])
    heading = "BEV: every frame moved into frame 0 by its pose\n(colour = frame; white = the sensor's path)"
    draw_bev(bev, np.concatenate(moved)[order], colors[order], extent=40.0, title=heading)
    path_xy = relative[:, :2, 3]
    bev.plot(path_xy[:, 0], path_xy[:, 1], color="white", linewidth=1.0, marker="o", markersize=3)
    frame_legend(bev, palette)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
