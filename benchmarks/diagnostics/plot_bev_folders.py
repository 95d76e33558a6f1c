"""What do the scans of a few SemanticKITTI-layout folders (real, through an autoencoder, generated) look like?

    python benchmarks/diagnostics/plot_bev_folders.py --folder real=DIR --folder generated=BANK ... --png OUT.png

One column per folder: its --index-th scan (sorted) in bird's-eye view (±--extent m, height colours) above its
64x1024 HDL-64E range image (log depth). The folders need no manifest: the gates' work folders (real, real projected,
real autoencoded) and banks of `u4d generate` alike. Answers "are the walls lines or stars?" for
`results/generation/pilots.md` (latent_pilot.png).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from u4d_aug.data.formats import read_kitti_scan  # noqa: E402
from u4d_aug.data.sensors import get_sensor  # noqa: E402
from u4d_aug.errors import InputError, exit_code_of  # noqa: E402
from u4d_aug.range_view import project  # noqa: E402
from u4d_aug.viz import draw_bev, draw_range_image, save_figure  # noqa: E402

LOG_DEPTH_RANGE = (0.0, float(np.log(80.0)))  # the range images' colour scale: 1 m to 80 m


def scan_of(folder: Path, index: int) -> Path:
    """The index-th scan (sorted) of a SemanticKITTI-layout folder."""
    scans = sorted(folder.glob("sequences/*/velodyne/*.bin"))
    if len(scans) <= index:
        raise InputError(f"{folder}: {len(scans)} scans under sequences/*/velodyne, need more than --index {index}")
    return scans[index]


def depth_image(points: np.ndarray) -> np.ndarray:
    """(64, 1024) log depth of a scan's HDL-64E beam-row range image, NaN where no return."""
    projection = project(torch.from_numpy(points), get_sensor("hdl64"), 64, 1024, "beam")
    depth = projection.depth.numpy()
    return np.where(depth > 0, np.log(np.maximum(depth, 1e-6)), np.nan)


def run(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", action="append", default=[], metavar="NAME=DIR", help="a folder (repeatable)")
    parser.add_argument("--index", type=int, default=0, help="which scan of each folder (sorted)")
    parser.add_argument("--extent", type=float, default=30.0, help="half width of the BEV in metres")
    parser.add_argument("--png", type=Path, required=True, help="output PNG")
    args = parser.parse_args(argv)
    folders = {}
    for text in args.folder:
        name, sep, folder = text.partition("=")
        if not sep or not name or not Path(folder).is_dir():
            raise InputError(f"--folder {text!r}: expected NAME=DIR with DIR a folder")
        folders[name] = Path(folder)
    if not folders:
        raise InputError("--folder: give at least one NAME=DIR")
    fig, axes = plt.subplots(2, len(folders), figsize=(5 * len(folders), 7), squeeze=False,
                             gridspec_kw={"height_ratios": [4, 1]})  # fmt: skip
    for column, (name, folder) in enumerate(folders.items()):
        path = scan_of(folder, args.index)
        points = read_kitti_scan(path)
        last = column == len(folders) - 1  # one colour bar per row: every panel of a row shares its scale
        draw_bev(axes[0, column], points, extent=args.extent, title=f"{name}\n{path.name}", point_size=0.4,
                 height_colorbar=last)  # fmt: skip
        draw_range_image(axes[1, column], depth_image(points), "log depth", vmin=LOG_DEPTH_RANGE[0],
                         vmax=LOG_DEPTH_RANGE[1], unit="ln(depth / 1 m)" if last else None)  # fmt: skip
        print(f"{name}: {path} ({len(points)} points)")
    save_figure(fig, args.png)
    return 0


def main(argv: list[str] | None = None) -> int:
    return exit_code_of(run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
