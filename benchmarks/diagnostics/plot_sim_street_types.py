"""One simulated scan of each street type (u4d_aug/data/sim/scenes.py), bird's-eye view coloured by class.

Every panel is frame `--frame` of place 0 of a world whose places all have that type (seed `--seed`, default
config otherwise), so the panels differ only by what the type lays out. Writes
benchmarks/results/world/sim_street_types.png.

    python benchmarks/diagnostics/plot_sim_street_types.py [--seed 1] [--frame 0] [--extent 40]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from u4d_aug.config import load_config
from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, map_semantickitti
from u4d_aug.data.sensors import hdl64
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.scenes import STREET_TYPES
from u4d_aug.data.sim.writer import build_sequence, render_frame
from u4d_aug.viz import draw_bev, label_colors, plt, save_figure

RESULTS = Path(__file__).resolve().parents[1] / "results" / "world"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--extent", type=float, default=40.0)
    parser.add_argument("--config", default="sim/varied", help="preset whose sensor model and objects are used")
    args = parser.parse_args()
    cols = 4
    rows = int(np.ceil((len(STREET_TYPES) + 1) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 6 * rows), squeeze=False)
    for ax, kind in zip(axes.ravel(), STREET_TYPES):
        weights = [f"street_types.{name}={1.0 if name == kind else 0.0}" for name in STREET_TYPES]
        cfg = load_config(SimConfig, args.config, weights)
        seq = build_sequence(args.seed, 0, args.frame + 1, hdl64(), cfg)
        scan = render_frame(seq, args.frame)
        colors = label_colors(map_semantickitti(scan.semantic))
        draw_bev(ax, scan.points, colors, extent=args.extent, title=kind, point_size=0.4)
        print(f"{kind}: {len(scan.points)} points", flush=True)
    legend = axes.ravel()[len(STREET_TYPES)]
    legend.axis("off")
    swatches = label_colors(np.arange(len(SEMANTICKITTI_CLASSES)))
    for k, name in enumerate(SEMANTICKITTI_CLASSES):
        legend.scatter([0.1], [1.0 - k * 0.05], color=swatches[k], s=80)
        legend.text(0.16, 1.0 - k * 0.05, name, va="center", fontsize=11)
    legend.set_xlim(0, 1)
    legend.set_ylim(0.0, 1.05)
    for ax in axes.ravel()[len(STREET_TYPES) + 1 :]:
        ax.axis("off")
    fig.suptitle(f"street types of the simulated world (seed {args.seed}, frame {args.frame}, {args.config})")
    path = save_figure(fig, RESULTS / "sim_street_types.png")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
