"""`u4d gen-report`: real vs generated scans side by side, one PNG per shown sample.

Rows of range images: the real scan, its uncertainty map H(p) with P_u outlined, U4D's stage-1 output x0_u,
U4D's stage-2 output x0 and the baseline's x0; below them the BEVs of the real, U4D and baseline scans.
Generated scans are re-projected with the bank's own sensor, size and row mode (from its manifest). Sequence
banks (L > 1 frames per sample) show frame `--frame` of each sample.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from u4d_aug.bank import BankLayout, read_manifest
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.data.sensors import Sensor, get_sensor
from u4d_aug.errors import InputError
from u4d_aug.io import check_output_file, load_npy
from u4d_aug.range_view import RowMode, decode_depth, project
from u4d_aug.uncertainty import load_probs, probs_path, uncertain_range_view
from u4d_aug.validate import check_plain_name


@dataclass(frozen=True)
class Geometry:
    """Range-image geometry shared by the banks being compared, and the bank's frames per sample (L)."""

    sensor: Sensor
    height: int
    width: int
    row_mode: RowMode
    frames: int = 1


def bank_geometry(bank: Path) -> Geometry:
    """Sensor, H, W and row mode recorded in a bank's manifest."""
    manifest = read_manifest(bank)
    if manifest is None:
        raise InputError(f"{bank}: no manifest.json (expected a bank written by `u4d generate`)")
    missing = [k for k in ("sensor", "height", "width", "row_mode") if k not in manifest]
    if missing:
        raise InputError(f"{bank}/manifest.json: missing {', '.join(missing)}")
    frames = int(manifest.get("frames", 1))
    return Geometry(get_sensor(manifest["sensor"]), manifest["height"], manifest["width"], manifest["row_mode"], frames)


def depth_image(points: np.ndarray, geometry: Geometry) -> np.ndarray:
    """(N, >=3) points -> (H, W) depth in metres, NaN where no return."""
    projection = project(torch.from_numpy(np.ascontiguousarray(points[:, :4])), geometry.sensor, geometry.height,
                         geometry.width, geometry.row_mode)  # fmt: skip
    depth = projection.depth.numpy()
    return np.where(projection.mask.numpy(), depth, np.nan)


def stage1_depth(layout: BankLayout, index: int, sensor: Sensor, frame: int = 0) -> np.ndarray | None:
    """Stage-1 x0_u of frame `frame` of sample `index` as (H, W) metres (NaN off the mask), if the bank kept it."""
    path = layout.stage1_path(index, frame)
    if not path.is_file():
        return None
    x0_u = torch.from_numpy(load_npy(path, "stage-1 image").astype(np.float32))  # (2, H, W) in [-1, 1]
    depth = decode_depth(x0_u[0], sensor.max_range).numpy()
    return np.where(x0_u[0].numpy() > -1.0, depth, np.nan)


def bank_scan(bank: Path, index: int, frame: int = 0) -> np.ndarray:
    """Points of frame `frame` of bank sample `index` (InputError if it was not generated or came out empty)."""
    frames = bank_geometry(bank).frames
    if not 0 <= frame < frames:
        raise InputError(f"{bank}: --frame {frame} outside the bank's frames 0..{frames - 1}")
    layout = BankLayout(bank, frames)
    if layout.is_empty(index, frame):
        raise InputError(f"{bank}: sample {index} has no return (listed under empty); choose another --index")
    return read_kitti_scan(layout.scan_path(index, frame))


def comparison_rows(
    real: np.ndarray,
    generated: dict[str, np.ndarray],
    geometry: Geometry,
    uncertainty: tuple[np.ndarray, np.ndarray] | None = None,
    stage1: np.ndarray | None = None,
) -> list[tuple[str, np.ndarray, str, str]]:
    """The range-image rows of the comparison: (title, (H, W) image, colour map, colour-bar label with unit)."""
    from u4d_aug.viz import DEPTH_LABEL, ENTROPY_LABEL

    rows = [("real: depth (black: no return)", depth_image(real, geometry), "turbo", DEPTH_LABEL)]
    if uncertainty is not None:
        rows.append(("real: uncertainty, entropy H(p) of the class probabilities; P_u outlined in cyan",
                     uncertainty[0], "magma", ENTROPY_LABEL))  # fmt: skip
    if stage1 is not None:
        rows.append(("U4D stage 1: x0_u, depth of the uncertain region", stage1, "turbo", DEPTH_LABEL))
    for name, points in generated.items():
        rows.append((f"{name}: depth", depth_image(points, geometry), "turbo", DEPTH_LABEL))
    return rows


def plot_comparison(
    path: Path,
    real: np.ndarray,
    generated: dict[str, np.ndarray],
    geometry: Geometry,
    uncertainty: tuple[np.ndarray, np.ndarray] | None = None,
    stage1: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """One PNG: range-image rows (real, uncertainty, stage 1, each bank) above a row of BEVs (real, each bank)."""
    import matplotlib.pyplot as plt

    from u4d_aug.viz import draw_bev, draw_range_image, save_figure, top_margin

    rows = comparison_rows(real, generated, geometry, uncertainty, stage1)
    vmax = float(np.nanpercentile(rows[0][1], 99)) if np.isfinite(rows[0][1]).any() else geometry.sensor.max_range

    n_bev = 1 + len(generated)
    fig = plt.figure(figsize=(4.4 * n_bev, 1.4 * len(rows) + 4.6))
    grid = fig.add_gridspec(len(rows) + 1, n_bev, height_ratios=[1.4] * len(rows) + [4.6], wspace=0.45, hspace=0.4,
                            top=top_margin(fig))  # fmt: skip
    for r, (label, image, cmap, unit) in enumerate(rows):
        ax = fig.add_subplot(grid[r, :])
        limits = (0.0, vmax) if cmap == "turbo" else (0.0, float(np.nanmax(image)) if np.isfinite(image).any() else 1)
        draw_range_image(ax, image, label, cmap=cmap, vmin=limits[0], vmax=limits[1], unit=unit)
        if cmap == "magma" and uncertainty is not None:
            ax.contour(uncertainty[1], levels=[0.5], colors="cyan", linewidths=0.5)
    for c, (name, points) in enumerate([("real", real), *generated.items()]):
        draw_bev(fig.add_subplot(grid[-1, c]), points, title=f"{name}: BEV by height ({len(points):,} points)")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def gen_report(
    real_root: Path,
    banks: dict[str, Path],
    png: Path,
    sequences: list[str] | None = None,
    probs_root: Path | None = None,
    index: int = 0,
    k: float = 0.1,
    frame: int = 0,
) -> Path:
    """Compare real scan `index` of `real_root` with frame `frame` of sample `index` of each bank (stage 1 from
    the bank named u4d)."""
    if not banks:
        raise InputError("--bank: give at least one NAME=DIR bank to compare")
    geometry = bank_geometry(next(iter(banks.values())))
    scans = ScanDataset(real_root, sequences)
    if len(scans) == 0:
        raise InputError(f"{real_root}: no scans")
    item = scans[index % len(scans)]
    real = item["points"]
    uncertainty = None
    if probs_root is not None:
        probs = load_probs(probs_path(probs_root, item["seq"], item["frame"]), len(real))
        _, m_u, entropy_image = uncertain_range_view(
            real, probs, geometry.sensor, geometry.height, geometry.width, geometry.row_mode, k, "entropy"
        )
        uncertainty = (entropy_image.numpy(), m_u[0].numpy())
    stage1 = None
    generated = {name: bank_scan(bank, index, frame) for name, bank in banks.items()}
    if "u4d" in banks:
        layout = BankLayout(banks["u4d"], bank_geometry(banks["u4d"]).frames)
        stage1 = stage1_depth(layout, index, geometry.sensor, frame)
    shown = f"sample {index}" if geometry.frames == 1 else f"sample {index}, frame {frame} of {geometry.frames}"
    title = f"real {item['seq']}/{item['frame']} vs generated {shown}"
    return plot_comparison(png, real, generated, geometry, uncertainty, stage1, title)


def _bank_argument(text: str) -> tuple[str, Path]:
    name, sep, folder = text.partition("=")
    if not sep or not name or not folder:
        raise argparse.ArgumentTypeError(f"expected NAME=DIR (e.g. u4d=banks/u4d), got {text!r}")
    try:
        check_plain_name(name, "bank name")
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return name, Path(folder)


def add_gen_report_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d gen-report REAL --bank NAME=DIR [--bank ...] --png OUT [--probs P] [--index I]`."""
    parser.add_argument("real", type=Path, help="SemanticKITTI-layout root of real (or held-out simulated) scans")
    parser.add_argument("--bank", type=_bank_argument, action="append", default=[], metavar="NAME=DIR",
                        help="a generated bank; the one named u4d also shows its stage-1 output")  # fmt: skip
    parser.add_argument("--png", type=Path, required=True, help="output PNG")
    parser.add_argument("--sequences", nargs="*", default=None, help="sequences of REAL to draw from")
    parser.add_argument("--probs", type=Path, default=None, help="seg-predict probabilities of REAL (uncertainty)")
    parser.add_argument("--index", type=int, default=0, help="which real scan and which bank sample")
    parser.add_argument("--k", type=float, default=0.1, help="fraction of points in P_u for the outline")
    parser.add_argument("--frame", type=int, default=0, help="frame of each sample in sequence banks (L > 1)")


def run_gen_report(args: argparse.Namespace) -> int:
    """`u4d gen-report`: write the side-by-side PNG."""
    if args.index < 0 or args.frame < 0:
        raise InputError(f"--index and --frame must be >= 0, got {args.index} and {args.frame}")
    check_output_file(args.png, "figure")
    path = gen_report(args.real, dict(args.bank), args.png, args.sequences, args.probs, args.index, args.k, args.frame)
    print(f"wrote {path}")
    return 0
