"""The `u4d` command: one sub-command per job; the only u4d_aug module that may import `segmentation` (lazily)."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from u4d_aug import __version__
from u4d_aug.errors import InputError


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `u4d` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if argv and argv[0] in dict(DELEGATED):
        # The implementing module parses everything after the command name (incl. its own --help).
        args = argparse.Namespace(command=argv[0], func=run_delegated, delegated=argv[0], rest=argv[1:])
    else:
        args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    warnings.simplefilter("default")
    warnings.formatwarning = lambda message, category, *a, **k: f"warning: {message}\n"
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; finished files are kept and a re-run resumes", file=sys.stderr)
        return 130


def build_parser() -> argparse.ArgumentParser:
    """All sub-commands, in the order of the data flow (DESIGN.md §3)."""
    parser = argparse.ArgumentParser(
        prog="u4d",
        description="U4D: uncertainty-aware 4D LiDAR scene synthesis as segmentation data augmentation.",
    )
    parser.add_argument("--version", action="version", version=f"u4d-aug {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("info", help="summarise a SemanticKITTI-layout root: sequences, frames, points, classes")
    p.add_argument("root", type=Path)
    p.add_argument("--json", action="store_true", help="print json instead of a table")
    p.set_defaults(func=run_info)

    p = sub.add_parser("show", help="render one scan: range image + BEV to PNG, .ply export, projection stats")
    p.add_argument("scan", type=Path, help="a KITTI .bin or a nuScenes .pcd.bin")
    p.add_argument("--sensor", default=None, help="hdl64 | hdl32 | sensor yaml (default: from the file type)")
    p.add_argument("--width", type=int, default=None, help="range-image width (default: the sensor's)")
    p.add_argument("--row-mode", choices=["beam", "linear"], default="beam")
    p.add_argument("--png", type=Path, default=None, help="write the picture here")
    p.add_argument("--ply", type=Path, default=None, help="export the points as .ply (open3d)")
    p.add_argument("--json", action="store_true", help="print projection statistics as json")
    p.set_defaults(func=run_show)

    p = sub.add_parser("demo", help="the main job end to end on the built-in simulated world (small, CPU)")
    p.add_argument("--out", type=Path, default=Path("outputs/demo"), help="everything goes here")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--real",
        type=Path,
        default=None,
        help="real SemanticKITTI root for the realism report (default: ../shared/data/real/semantickitti when present)",
    )
    p.set_defaults(func=run_demo)

    for name, help_text in DELEGATED:
        p = sub.add_parser(name, help=help_text, add_help=False)
        p.add_argument("rest", nargs=argparse.REMAINDER)
        p.set_defaults(func=run_delegated, delegated=name)
    return parser


# Commands whose arguments live beside their implementation; each module is imported only when its command runs
# (so `u4d --help` stays fast and u4d_aug never imports segmentation at import time).
DELEGATED = (
    ("simulate", "write a simulated 4D LiDAR world in SemanticKITTI layout"),
    ("sim-report", "compare simulated scans with real ones: histograms, JS distance, PNG"),
    ("seg-train", "train a segmentation net (supervised or semi-supervised), torchrun-ready"),
    ("seg-eval", "mIoU, per-class IoU, ECE (per scan and pooled), reliability diagram of a checkpoint"),
    ("seg-predict", "write per-point class probabilities (float16 .npy) for U4D's uncertainty"),
    ("train-diffusion", "train a U4D stage (stage1 | stage2) or the R2DM-style baseline, torchrun-ready"),
    ("generate", "write a bank of generated scans (U4D, baseline or completion of real scans), torchrun-ready"),
    ("gen-report", "real vs generated scans side by side: uncertainty, stage-1, stage-2, baseline; range + BEV PNG"),
    ("train-extractor", "train the FRD (range-view) or FPD (PointNet) feature extractor on labeled scans"),
    ("export-weights", "float16 inference weights + config + hash of a trained net (diffusion, extractor, segmentor)"),
    ("evaluate", "generation metrics of a bank vs real scans: FRD, FPD, BEV JSD/MMD (Table 1), TTCE/CTC (Table 2)"),
    ("experiment", "sup-only / LaserMix / +R2DM bank / +U4D bank comparison: mIoU and ECE over seeds"),
)


def _delegated_module(name: str):
    """Import the module that implements a delegated command (explicit choices, no registry)."""
    import importlib

    if name == "simulate":
        return importlib.import_module("u4d_aug.data.sim.writer"), "simulate"
    elif name == "sim-report":
        return importlib.import_module("u4d_aug.data.sim.report"), "sim_report"
    elif name == "seg-train":
        return importlib.import_module("segmentation.train"), "seg_train"
    elif name == "seg-eval":
        return importlib.import_module("segmentation.evaluate"), "seg_eval"
    elif name == "seg-predict":
        return importlib.import_module("segmentation.predict"), "seg_predict"
    elif name == "train-diffusion":
        return importlib.import_module("u4d_aug.train"), "train_diffusion"
    elif name == "generate":
        return importlib.import_module("u4d_aug.generate"), "generate"
    elif name == "gen-report":
        return importlib.import_module("u4d_aug.gen_report"), "gen_report"
    elif name == "train-extractor":
        return importlib.import_module("u4d_aug.metrics.extractors"), "train_extractor"
    elif name == "export-weights":
        return importlib.import_module("u4d_aug.weights"), "export_weights"
    elif name == "evaluate":
        return importlib.import_module("u4d_aug.metrics.evaluate"), "evaluate"
    elif name == "experiment":
        return importlib.import_module("segmentation.experiment"), "experiment"
    raise ValueError(f"unknown command {name!r}; allowed: {', '.join(n for n, _ in DELEGATED)}")


def run_delegated(args: argparse.Namespace) -> int:
    """Parse the rest of the command line with the implementing module's own arguments, then run it."""
    module, stem = _delegated_module(args.delegated)
    help_text = dict(DELEGATED)[args.delegated]
    parser = argparse.ArgumentParser(prog=f"u4d {args.delegated}", description=help_text)
    getattr(module, f"add_{stem}_arguments")(parser)
    return int(getattr(module, f"run_{stem}")(parser.parse_args(args.rest)) or 0)


# ----------------------------------------------------------------------------------------------------------------
# info


def run_info(args: argparse.Namespace) -> int:
    """`u4d info ROOT`: what a dataset root holds."""
    from u4d_aug.data.datasets import list_frames, list_sequences
    from u4d_aug.data.formats import label_path_for, load_kitti_frame
    from u4d_aug.data.labels import SEMANTICKITTI_CLASSES, SEMANTICKITTI_IGNORE, map_semantickitti

    root = args.root
    sequences = list_sequences(root)
    per_sequence = []
    counts = np.zeros(len(SEMANTICKITTI_CLASSES) + 1, dtype=np.int64)
    num_points = []
    for seq in sequences:
        frames = list_frames(root, seq)
        labeled = 0
        for frame in frames:
            scan_path = root / "sequences" / seq / "velodyne" / f"{frame}.bin"
            label_path = label_path_for(scan_path)
            has_label = label_path.is_file()
            loaded = load_kitti_frame(scan_path, label_path if has_label else None)
            num_points.append(len(loaded.points))
            if has_label:
                labeled += 1
                train_ids = map_semantickitti(loaded.semantic)
                counts += np.bincount(train_ids, minlength=len(counts))[: len(counts)]
        per_sequence.append({"sequence": seq, "frames": len(frames), "labeled_frames": labeled})
    pts = np.asarray(num_points) if num_points else np.zeros(1)
    classes = {name: int(counts[i]) for i, name in enumerate(SEMANTICKITTI_CLASSES)}
    classes["ignore"] = int(counts[SEMANTICKITTI_IGNORE])
    summary = {
        "root": str(root),
        "sequences": per_sequence,
        "frames": int(sum(s["frames"] for s in per_sequence)),
        "labeled_frames": int(sum(s["labeled_frames"] for s in per_sequence)),
        "points_per_scan": {"mean": float(pts.mean()), "min": int(pts.min()), "max": int(pts.max())},
        "class_histogram": classes,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"root: {root}")
    for s in per_sequence:
        print(f"  sequence {s['sequence']}: {s['frames']} frames, {s['labeled_frames']} labeled")
    pps = summary["points_per_scan"]
    print(f"points/scan: mean {pps['mean']:.0f}, min {pps['min']}, max {pps['max']}")
    total = max(int(counts.sum()), 1)
    if counts.sum():
        print("class histogram (labeled frames, train ids):")
        for i, name in enumerate([*SEMANTICKITTI_CLASSES, "ignore"]):
            print(f"  {i:2d} {name:<14s} {counts[i]:>10d}  {100.0 * counts[i] / total:5.1f}%")
    return 0


# ----------------------------------------------------------------------------------------------------------------
# show


# ----------------------------------------------------------------------------------------------------------------
# demo


# The yaml presets live at the top of the repository, beside the package.
CONFIGS_DIR = Path(__file__).resolve().parents[1] / "configs"


def run_demo(args: argparse.Namespace) -> int:
    """`u4d demo`: every stage that exists, in the order of DESIGN.md §3, each through its own command."""
    out = args.out
    world = out / "world"
    real = args.real or Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "semantickitti"
    frame0 = world / "sequences" / "00" / "velodyne" / "000000.bin"
    steps = [
        (
            "simulate a small world (3 sequences x 6 frames, HDL-64E)",
            ["simulate", "--out", str(world), "--sequences", "3", "--frames", "6", "--seed", str(args.seed)],
        ),
        ("summarise it", ["info", str(world)]),
        ("picture of frame 0: range image + BEV", ["show", str(frame0), "--png", str(out / "frame0.png")]),
    ]
    if (real / "sequences").is_dir():
        steps.append(
            (
                "realism report against the real scans",
                [
                    "sim-report",
                    str(world),
                    "--real",
                    str(real),
                    "--png",
                    str(out / "sim_vs_real.png"),
                    "--max-frames",
                    "6",
                ],
            )
        )
    seg_dir = out / "seg"
    steps += [
        (
            "train a small MinkUNet-like segmentor (sequences 00-01, held-out 02)",
            [
                "seg-train",
                "configs/seg/tiny.yaml",
                f"data.root={world}",
                'data.train_sequences=["00", "01"]',
                'data.val_sequences=["02"]',
                "optim.steps=40",
                "eval_every=20",
                "checkpoint_every=20",
                f"seed={args.seed}",
                "--out",
                str(seg_dir),
            ],
        ),
        (
            "evaluate it: mIoU, ECE, reliability diagram",
            [
                "seg-eval",
                str(seg_dir / "model.pt"),
                str(world),
                "--sequences",
                "02",
                "--png",
                str(out / "reliability.png"),
            ],
        ),
        (
            "per-point probabilities for U4D's uncertainty",
            ["seg-predict", str(seg_dir / "model.pt"), str(world), "--out", str(out / "probs")],
        ),
    ]
    diffusion = ["configs/u4d/demo.yaml", f"data_root={world}", 'sequences=["00", "01"]', f"seed={args.seed}"]
    probs = f"probs_root={out / 'probs'}"
    banks = {"u4d": out / "bank_u4d", "baseline": out / "bank_baseline"}
    generate = ["configs/u4d/generate_cpu.yaml", "steps=16", "stage1_steps=8", "num=4", f"seed={args.seed}"]
    steps += [
        ("U4D stage 1: diffusion of the uncertain region P_u + mask head",
         ["train-diffusion", *diffusion, "stage=stage1", probs, "--out", str(out / "u4d_stage1")]),
        ("U4D stage 2: completion conditioned on (x0_u, m_u)",
         ["train-diffusion", *diffusion, "stage=stage2", probs, "--out", str(out / "u4d_stage2")]),
        ("R2DM-style baseline: one unconditional stage",
         ["train-diffusion", *diffusion, "stage=baseline", "--out", str(out / "baseline")]),
        ("generate 4 scans hard-to-easy with U4D",
         ["generate", *generate, "mode=u4d", f"stage1={out / 'u4d_stage1'}", f"stage2={out / 'u4d_stage2'}",
          "--out", str(banks["u4d"])]),
        ("generate 4 scans with the baseline",
         ["generate", *generate, "mode=baseline", f"baseline={out / 'baseline'}", "--out", str(banks["baseline"])]),
        ("real vs U4D vs baseline: uncertainty, stage 1, stage 2, BEV",
         ["gen-report", str(world), "--sequences", "02", "--probs", str(out / "probs"),
          "--bank", f"u4d={banks['u4d']}", "--bank", f"baseline={banks['baseline']}",
          "--png", str(out / "generated.png")]),
    ]  # fmt: skip
    for name, bank in banks.items():
        steps.append(
            (f"generation metrics of the {name} bank vs held-out sequence 02 (BEV JSD/MMD, CTC)",
             ["evaluate", "--bank", str(bank), "--real", str(world), "--real-sequences", "02",
              "--metrics", "jsd,mmd,ctc", "--json", "--md", "--out", str(out / f"eval_{name}")])
        )  # fmt: skip
    print(
        "u4d demo: every stage at toy size (minutes on 2 CPU cores). Not run here: the LaserMix mean-teacher "
        "comparison (`u4d experiment`, hours) and FRD/FPD (need trained extractors: `u4d train-extractor`)."
    )
    for number, (title, command) in enumerate(steps, start=1):
        command = _resume_if_started(command)
        print(f"\n[{number}/{len(steps)}] {title}\n$ u4d {' '.join(command)}", flush=True)
        status = main(command)
        if status != 0:
            print(f"demo stopped at step {number} (exit {status}); re-run to resume", file=sys.stderr)
            return status
    print(f"\ndemo done: outputs in {out}")
    return 0


def _resume_if_started(command: list[str]) -> list[str]:
    """A training step of a re-run demo continues from its newest checkpoint (a finished one just returns)."""
    if command[0] not in ("seg-train", "train-diffusion") or "--out" not in command:
        return command
    out = Path(command[command.index("--out") + 1])
    return [*command, "--resume"] if any((out / "checkpoints").glob("step_*.pt")) else command


def _load_any_scan(path: Path) -> tuple[np.ndarray, np.ndarray | None, str]:
    """A KITTI .bin (with labels beside it when present) or a nuScenes .pcd.bin -> points, train ids, sensor name."""
    from u4d_aug.data.formats import label_path_for, load_kitti_frame, read_nuscenes_scan
    from u4d_aug.data.labels import map_semantickitti

    if path.name.endswith(".pcd.bin"):
        return read_nuscenes_scan(path).points, None, "hdl32"
    label_path = label_path_for(path)
    frame = load_kitti_frame(path, label_path if label_path.is_file() else None)
    labels = map_semantickitti(frame.semantic) if frame.semantic is not None else None
    return frame.points, labels, "hdl64"


def run_show(args: argparse.Namespace) -> int:
    """`u4d show SCAN`: picture, .ply and projection round-trip statistics of one scan."""
    import torch

    from u4d_aug.data.sensors import get_sensor
    from u4d_aug.range_view import project, roundtrip_stats, scatter_to_image

    points, labels, default_sensor = _load_any_scan(args.scan)
    sensor = get_sensor(args.sensor or default_sensor)
    width = args.width or sensor.width
    height = sensor.height
    stats = roundtrip_stats(torch.from_numpy(points), sensor, height, width, args.row_mode)
    stats = {
        "scan": str(args.scan),
        "sensor": sensor.name,
        "height": height,
        "width": width,
        "row_mode": args.row_mode,
        **{k: float(v) if k != "points" else int(v) for k, v in stats.items()},
    }
    if args.png is not None:
        from u4d_aug.viz import plot_scan

        proj = project(torch.from_numpy(points), sensor, height, width, args.row_mode)
        label_image = None
        if labels is not None:
            label_image = scatter_to_image(torch.from_numpy(labels), proj, fill=-1).numpy()
        plot_scan(
            args.png,
            points,
            proj.depth.numpy(),
            proj.reflectance.numpy(),
            labels,
            label_image,
            title=f"{args.scan.name}  {sensor.name} {height}x{width} ({args.row_mode})",
        )
        stats["png"] = str(args.png)
    if args.ply is not None:
        _write_ply(args.ply, points, labels)
        stats["ply"] = str(args.ply)
    if args.json:
        print(json.dumps(stats, indent=2))
    else:
        for key, value in stats.items():
            print(f"{key}: {value}")
    return 0


def _write_ply(path: Path, points: np.ndarray, labels: np.ndarray | None) -> None:
    """Export points (coloured by label, else by intensity) with open3d, atomically."""
    import os
    import tempfile

    import open3d as o3d

    from u4d_aug.viz import label_colors

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[:, :3].astype(np.float64)))
    colors = label_colors(labels) if labels is not None else np.repeat(points[:, 3:4], 3, axis=1)
    cloud.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".ply", dir=path.parent)
    os.close(fd)
    try:
        if not o3d.io.write_point_cloud(tmp, cloud):
            raise InputError(f"{path}: open3d could not write the .ply file")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


if __name__ == "__main__":
    raise SystemExit(main())
