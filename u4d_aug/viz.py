"""Pictures a person would rather look at than read: range images, BEV, uncertainty maps (matplotlib, Agg)."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

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


def label_colors(labels: np.ndarray, num_classes: int = 19) -> np.ndarray:
    """(N,) train ids -> (N, 3) RGB in [0, 1]; SemanticKITTI palette for 19 classes, tab20 otherwise."""
    labels = np.asarray(labels)
    if num_classes == 19:
        return SEMANTICKITTI_COLORS[np.clip(labels, 0, 19)]
    palette = plt.get_cmap("tab20")(np.arange(20))[:, :3]
    colors = palette[np.clip(labels, 0, 19) % 20]
    colors[labels >= num_classes] = 0.0
    return colors


def save_figure(fig: plt.Figure, path: str | Path, dpi: int = 110) -> Path:
    """Render a figure to PNG bytes and write them atomically; closes the figure."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    return Path(path)


def draw_range_image(ax: plt.Axes, image: np.ndarray, title: str, cmap: str = "turbo", vmin=None, vmax=None):
    """One (H, W) channel; NaN pixels (no return) drawn black. Wide images get a squashed aspect to stay readable."""
    height, width = image.shape
    cm = plt.get_cmap(cmap).with_extremes(bad="black")
    handle = ax.imshow(image, cmap=cm, vmin=vmin, vmax=vmax, interpolation="nearest", aspect=max(width / height / 8, 1))
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
):
    """Bird's-eye view scatter of (N, >=3) points inside +-extent metres; colour by `colors` or by height."""
    points = np.asarray(points)
    inside = (np.abs(points[:, 0]) < extent) & (np.abs(points[:, 1]) < extent)
    pts = points[inside]
    if colors is None:
        z = pts[:, 2]
        c = plt.get_cmap("viridis")(np.clip((z + 3.0) / 6.0, 0.0, 1.0))[:, :3]
    else:
        c = np.asarray(colors)[inside]
    ax.scatter(pts[:, 0], pts[:, 1], c=c, s=point_size, linewidths=0, rasterized=True)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    ax.set_facecolor("black")
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=7)


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
    """Range image (depth, reflectance, labels when known) above a BEV coloured by label or height."""
    rows = 3 if label_image is not None else 2
    fig = plt.figure(figsize=(12, 2.0 * rows + 6))
    grid = fig.add_gridspec(rows + 1, 1, height_ratios=[1] * rows + [4])
    depth = np.where(depth_image > 0, depth_image, np.nan)
    draw_range_image(fig.add_subplot(grid[0]), depth, "depth [m]", vmin=0, vmax=np.nanpercentile(depth, 99))
    refl = np.where(depth_image > 0, reflectance_image, np.nan)
    draw_range_image(fig.add_subplot(grid[1]), refl, "reflectance", cmap="gray", vmin=0, vmax=1)
    if label_image is not None:
        ax = fig.add_subplot(grid[2])
        rgb = label_colors(np.where(label_image >= 0, label_image, num_classes), num_classes)
        rgb[label_image < 0] = 0
        ax.imshow(rgb, interpolation="nearest", aspect=max(label_image.shape[1] / label_image.shape[0] / 8, 1))
        ax.set_title("labels", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    bev_ax = fig.add_subplot(grid[rows])
    colors = label_colors(labels, num_classes) if labels is not None else None
    draw_bev(bev_ax, points, colors, title="BEV (" + ("labels" if labels is not None else "height") + ")")
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


def plot_sequence(
    path: str | Path, depth_images: list[np.ndarray], clouds: list[np.ndarray], poses: np.ndarray, title: str = ""
) -> Path:
    """An L-frame sequence: each frame's depth image, above a BEV of every frame moved into frame 0 by its pose.

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
    grid = fig.add_gridspec(frames, 2, width_ratios=[12, 6.5], wspace=0.05, hspace=0.4)
    finite = np.concatenate([d[d > 0].ravel() for d in depth_images] + [np.ones(1)])
    top = float(np.percentile(finite, 99))
    for i, depth in enumerate(depth_images):
        ax = fig.add_subplot(grid[i, 0])
        draw_range_image(ax, np.where(depth > 0, depth, np.nan), f"frame {i}: depth [m]", vmin=0, vmax=top)
        ax.title.set_color(palette[i])
    moved = [np.asarray(c)[:, :3] @ relative[i, :3, :3].T + relative[i, :3, 3] for i, c in enumerate(clouds)]
    colors = np.concatenate([np.tile(palette[i], (len(m), 1)) for i, m in enumerate(moved)])
    order = np.random.default_rng(0).permutation(len(colors))  # frames interleaved, so no frame hides the others
    bev = fig.add_subplot(grid[:, 1])
    heading = "BEV: every frame moved into frame 0 by its pose\n(colour = frame; white = the sensor's path)"
    draw_bev(bev, np.concatenate(moved)[order], colors[order], extent=40.0, title=heading)
    path_xy = relative[:, :2, 3]
    bev.plot(path_xy[:, 0], path_xy[:, 1], color="white", linewidth=1.0, marker="o", markersize=3)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
