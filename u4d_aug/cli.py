"""The `u4d` command: one sub-command per job; the only u4d_aug module that may import `segmentation` (lazily).

The one launch path: `u4d COMMAND` in one process, `torchrun ... -m u4d_aug.cli COMMAND` in several.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from u4d_aug import __version__
from u4d_aug.cmdline import (
    VERBOSITY_FLAGS,
    CommandParser,
    add_verbosity_arguments,
    configure_logging,
    parse_command_line,
    split_verbosity,
)
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_save_npy, atomic_write_text, check_output_file, dumps_json
from u4d_aug.presets import configs_root
from u4d_aug.runlock import run_lock
from u4d_aug.weights_store import split_weights_dir

if TYPE_CHECKING:
    from u4d_aug.data.datasets import NuscenesScanDataset, ScanDataset


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `u4d` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, level = split_verbosity(argv)  # --quiet / --verbose anywhere
    configure_logging(level)
    try:
        argv = split_weights_dir(argv)  # --weights-dir anywhere: where the shipped nets are (u4d_aug.weights_store)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    parser = build_parser()
    if argv and argv[0] in dict(DELEGATED):
        # The implementing module parses everything after the command name (incl. its own --help).
        args = argparse.Namespace(command=argv[0], func=run_delegated, delegated=argv[0], rest=argv[1:])
    else:
        args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    args.log_level = level
    warnings.simplefilter("default")
    warnings.formatwarning = lambda message, category, *a, **k: f"warning: {message}\n"
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file system refusal the command did not name itself: still one line
        print(f"error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; finished files are kept and a re-run resumes", file=sys.stderr)
        return 130


def build_parser() -> argparse.ArgumentParser:
    """All sub-commands, in the order of the data flow (DESIGN.md §3)."""
    parser = CommandParser(
        prog="u4d",
        description="U4D: uncertainty-aware 4D LiDAR scene synthesis as segmentation data augmentation.",
        epilog=f"example: {EXAMPLES['demo']}   (`u4d COMMAND --help` shows an example of each command)",
    )
    parser.add_argument("--version", action="version", version=f"u4d-aug {__version__}")
    add_verbosity_arguments(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = _command(sub, "info", "summarise a dataset root: sequences, frames, points, classes")
    p.add_argument("root", type=Path)
    p.add_argument(
        "--format",
        choices=["semantickitti", "nuscenes"],
        default=None,
        help="layout of ROOT: semantickitti (sequences/XX/velodyne) or nuscenes (v1.0 tables; scenes, keyframes); "
        "default: detected (sequences/: semantickitti; a v1.0-* folder or samples/LIDAR_TOP/: nuscenes)",
    )
    p.add_argument("--nuscenes-version", default="v1.0-trainval", help="--format nuscenes: the table folder")
    p.add_argument("--json", action="store_true", help="print json instead of a table")
    p.set_defaults(func=run_info)

    p = _command(sub, "show", "render one scan (range image + BEV, .ply, projection stats) or one sequence's frames")
    p.add_argument(
        "scan",
        type=Path,
        help="a KITTI .bin, a nuScenes .pcd.bin, or a SemanticKITTI sequence folder (velodyne/ + "
        "poses.txt + calib.txt, as `u4d generate frames=L` writes): its frames and a BEV of them moved by their poses",
    )
    p.add_argument("--sensor", default=None, help="hdl64 | hdl32 | sensor yaml (default: from the file type)")
    p.add_argument("--width", type=int, default=None, help="range-image width (default: the sensor's)")
    p.add_argument("--row-mode", choices=["beam", "linear"], default="beam")
    p.add_argument("--png", type=Path, default=None, help="write the picture here")
    p.add_argument("--ply", type=Path, default=None, help="export the points as .ply (open3d)")
    p.add_argument("--json", action="store_true", help="print projection statistics as json")
    p.set_defaults(func=run_show)

    p = _command(sub, "demo", "the main job end to end on the built-in simulated world (small, CPU)")
    p.add_argument("--out", type=Path, default=Path("outputs/demo"), help="everything goes here")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--real",
        type=Path,
        default=None,
        help="real SemanticKITTI root for the realism report (default: ../shared/data/real/semantickitti when present)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars (passed on to every step)")
    p.set_defaults(func=run_demo)

    for name, help_text in DELEGATED:
        p = sub.add_parser(name, help=help_text, add_help=False)
        p.add_argument("rest", nargs=argparse.REMAINDER)
        p.set_defaults(func=run_delegated, delegated=name)
    return parser


def _command(sub, name: str, help_text: str) -> argparse.ArgumentParser:
    """A sub-command whose --help ends with its example line and the global options."""
    parser = sub.add_parser(name, help=help_text, description=help_text, epilog=f"example: {EXAMPLES[name]}")
    add_verbosity_arguments(parser)
    return parser


# Commands whose arguments live beside their implementation; each module is imported only when its command runs
# (so `u4d --help` stays fast and u4d_aug never imports segmentation at import time).
DELEGATED = (
    ("simulate", "write a simulated 4D LiDAR world in SemanticKITTI layout"),
    ("sim-report", "compare simulated scans with real ones: histograms, JS distance, PNG"),
    ("seg-train", "train a segmentation net (supervised or semi-supervised), torchrun-ready"),
    ("seg-eval", "mIoU, per-class IoU, ECE (per scan and pooled), reliability diagram of a checkpoint"),
    ("seg-predict", "write per-point class probabilities (float16 .npy) for U4D's uncertainty"),
    ("train-diffusion", "train U4D (stage=u4d one net | stage1 | stage2) or the R2DM-style baseline, torchrun-ready"),
    ("train-autoencoder", "train the range-image autoencoder whose latent the latent generators diffuse (LiDM)"),
    ("generate", "write a bank of generated scans (U4D, baseline or completion of real scans), torchrun-ready"),
    ("gen-report", "real vs generated scans side by side: uncertainty, stage-1, stage-2, baseline; range + BEV PNG"),
    ("train-extractor", "train the FRD (range-view) or FPD (PointNet) feature extractor on labeled scans"),
    ("export-weights", "float16 inference weights + config + hash of a trained net (diffusion, extractor, segmentor)"),
    ("gates", "MoST gate analysis: mean spatial / temporal gate per block over the sampling of a sequence net"),
    ("evaluate", "generation metrics of a bank vs real scans: FRD, FPD, BEV JSD/MMD (Table 1), TTCE/CTC (Table 2)"),
    ("experiment", "sup-only / LaserMix / +R2DM bank / +U4D bank comparison: mIoU and ECE over seeds"),
    ("export", "a bank as another codebase reads it: --layout semantickitti|mmdet3d|pointcept [--out DIR]"),
    ("bank-real", "a bank of real scans of unused places, through the generators' range image (the ceiling arm)"),
    ("weights", "where the shipped nets are (list), or copy them from a checkout into the user cache (install)"),
)


def _load_segmentor(path: Path) -> object:
    """Load segmentation weights the way `u4d seg-predict` does (export-weights reads its file back with it)."""
    import torch

    from segmentation import predict

    return predict.model_from_checkpoint(predict.load_checkpoint(path), torch.device("cpu"), str(path))


def _delegated_command(name: str) -> tuple[Callable[[argparse.ArgumentParser], None], Callable[..., int]]:
    """(add_arguments, run) of a delegated command, importing its module only now (explicit choices, no registry)."""
    if name == "simulate":
        from u4d_aug.data.sim import writer

        return writer.add_simulate_arguments, writer.run_simulate
    elif name == "sim-report":
        from u4d_aug.data.sim import report

        return report.add_sim_report_arguments, report.run_sim_report
    elif name == "seg-train":
        from segmentation import train as seg_train

        return seg_train.add_seg_train_arguments, seg_train.run_seg_train
    elif name == "seg-eval":
        from segmentation import evaluate as seg_eval

        return seg_eval.add_seg_eval_arguments, seg_eval.run_seg_eval
    elif name == "seg-predict":
        from segmentation import predict

        return predict.add_seg_predict_arguments, predict.run_seg_predict
    elif name == "train-diffusion":
        from u4d_aug import train

        return train.add_train_diffusion_arguments, train.run_train_diffusion
    elif name == "train-autoencoder":
        from u4d_aug import train_autoencoder

        return train_autoencoder.add_train_autoencoder_arguments, train_autoencoder.run_train_autoencoder
    elif name == "generate":
        from u4d_aug import generate

        return generate.add_generate_arguments, generate.run_generate
    elif name == "gen-report":
        from u4d_aug import gen_report

        return gen_report.add_gen_report_arguments, gen_report.run_gen_report
    elif name == "train-extractor":
        from u4d_aug.metrics import extractors

        return extractors.add_train_extractor_arguments, extractors.run_train_extractor
    elif name == "export-weights":
        from u4d_aug import export_weights

        def run(args: argparse.Namespace) -> int:
            return export_weights.run_export_weights(args, load_segmentor=_load_segmentor)

        return export_weights.add_export_weights_arguments, run
    elif name == "gates":
        from u4d_aug import gates

        return gates.add_gates_arguments, gates.run_gates
    elif name == "evaluate":
        from u4d_aug.metrics import evaluate

        return evaluate.add_evaluate_arguments, evaluate.run_evaluate
    elif name == "experiment":
        from segmentation import experiment

        return experiment.add_experiment_arguments, experiment.run_experiment
    elif name == "export":
        from u4d_aug import export_bank

        return export_bank.add_export_arguments, export_bank.run_export
    elif name == "bank-real":
        from u4d_aug import real_bank

        return real_bank.add_bank_real_arguments, real_bank.run_bank_real
    elif name == "weights":
        from u4d_aug import weights_install

        return weights_install.add_weights_arguments, weights_install.run_weights
    raise ValueError(f"unknown command {name!r}; allowed: {', '.join(n for n, _ in DELEGATED)}")


# One example line per command, shown at the end of its --help (tests/u4d_aug/test_cli.py parses each of them).
EXAMPLES = {
    "info": "u4d info data/sim --json",
    "show": "u4d show data/sim/sequences/00/velodyne/000000.bin --png scan.png --ply scan.ply",
    "demo": "u4d demo --out outputs/demo",
    "simulate": "u4d simulate sim/seg_rich --out data/sim --sequences 2 --frames 20 --seed 0 agents.cars_per_100m=3",
    "sim-report": "u4d sim-report data/sim --real ../shared/data/real/semantickitti --png sim_vs_real.png",
    "seg-train": "u4d seg-train seg/cpu_minkunet data.root=data/sim --out runs/seg optim.steps=100",
    "seg-eval": "u4d seg-eval runs/seg/model.pt data/sim --sequences 02 --png reliability.png",
    "seg-predict": "u4d seg-predict runs/seg/model.pt data/sim --out runs/probs",
    "train-diffusion": "u4d train-diffusion u4d/cpu stage=u4d data_root=data/sim probs_root=runs/probs --out runs/u4d",
    "train-autoencoder": "u4d train-autoencoder u4d/autoencoder_hdl64 data_root=data/sim probs_root=runs/probs "
    "--out runs/autoencoder",
    "generate": "u4d generate u4d/generate_cpu --out banks/u4d net=runs/u4d stage1= stage2= num=16",
    "gen-report": "u4d gen-report data/sim --bank u4d=banks/u4d --bank baseline=banks/baseline --png generated.png",
    "train-extractor": "u4d train-extractor frd extractor/cpu data.root=data/semantickitti train.steps=500",
    "export-weights": "u4d export-weights runs/u4d --out weights/u4d.pt",
    "gates": "u4d gates runs/u4d_most_stage2 --png gates.png --json",
    "evaluate": "u4d evaluate --bank banks/u4d --real data/sim --real-sequences 02 --metrics jsd,mmd,ctc --md "
    "--out runs/eval_u4d",
    "experiment": "u4d experiment experiment/downstream_10pct --arms sup-only 'seeds=[0]'",
    "export": "u4d export banks/u4d --labels --mmdet3d-infos",
    "bank-real": "u4d bank-real data/sim_seg --sequences 100-163 --out banks/real_hdl64 --generator runs/u4d",
    "weights": "u4d weights install ~/src/u4d-aug",
}


def delegated_parser(name: str) -> tuple[argparse.ArgumentParser, Callable[[argparse.Namespace], int]]:
    """The parser of a delegated command (the module's own arguments, its example, the global options)."""
    add_arguments, run = _delegated_command(name)
    help_text = dict(DELEGATED)[name]
    parser = CommandParser(prog=f"u4d {name}", description=help_text, epilog=f"example: {EXAMPLES[name]}")
    add_arguments(parser)
    add_verbosity_arguments(parser)
    return parser, run


def run_delegated(args: argparse.Namespace) -> int:
    """Parse the rest of the command line with the implementing module's own arguments, then run it."""
    parser, run = delegated_parser(args.delegated)
    return int(run(parse_command_line(parser, args.rest)) or 0)


# ----------------------------------------------------------------------------------------------------------------
# info


def run_info(args: argparse.Namespace) -> int:
    """`u4d info ROOT`: what a dataset root holds (nuScenes: the keyframes of each scene)."""
    from u4d_aug.data.datasets import detect_format, open_scans

    root = args.root
    data_format = args.format or detect_format(root)
    dataset = open_scans(root, None, False, data_format, args.nuscenes_version)
    summary = dataset_summary(dataset, root, data_format)
    if args.json:
        print(dumps_json(summary, indent=2))
        return 0
    print(f"root: {root} ({data_format})")
    for s in summary["sequences"]:
        all_ignore = f", {s['all_ignore_frames']} all-ignore" if s["all_ignore_frames"] else ""
        print(f"  sequence {s['sequence']}: {s['frames']} frames, {s['labeled_frames']} labeled{all_ignore}")
    label_files = summary["labeled_frames"] + summary["all_ignore_frames"]
    apart = " (not counted as labeled)" if summary["all_ignore_frames"] else ""
    print(f"labels: {label_files} scans, {summary['all_ignore_frames']} of them all-ignore{apart}")
    pps = summary["points_per_scan"]
    print(f"points/scan: mean {pps['mean']:.0f}, min {pps['min']}, max {pps['max']}")
    counts = list(summary["class_histogram"].items())
    total = sum(count for _, count in counts)
    if total:
        print("class histogram (labeled frames, train ids):")
        width = max(14, *(len(name) for name, _ in counts))
        for i, (name, count) in enumerate(counts):
            print(f"  {i:2d} {name:<{width}s} {count:>10d}  {100.0 * count / total:5.1f}%")
    return 0


def dataset_summary(dataset: ScanDataset | NuscenesScanDataset, root: Path, data_format: str) -> dict:
    """Frames, labeled frames (scans whose labels are all ignore counted apart), points per scan and the class
    histogram of the labeled frames, per sequence and in all."""
    names = dataset.label_set.classes
    ignore = dataset.label_set.ignore_index
    per_sequence = {
        seq: {"sequence": seq, "frames": 0, "labeled_frames": 0, "all_ignore_frames": 0} for seq in dataset.sequences
    }
    counts = np.zeros(len(names) + 1, dtype=np.int64)
    num_points = []
    for index in range(len(dataset)):
        item = dataset[index]
        num_points.append(len(item["points"]))
        sequence = per_sequence[item["seq"]]
        sequence["frames"] += 1
        if item["labels"] is None:
            continue
        elif np.all(item["labels"] == ignore):  # a label file of unlabeled points (an exported bank's): no labels
            sequence["all_ignore_frames"] += 1
        else:
            sequence["labeled_frames"] += 1
            counts += np.bincount(item["labels"], minlength=len(counts))[: len(counts)]
    sequences = list(per_sequence.values())
    pts = np.asarray(num_points) if num_points else np.zeros(1)
    classes = {name: int(counts[i]) for i, name in enumerate(names)}
    classes["ignore"] = int(counts[len(names)])
    return {
        "root": str(root),
        "format": data_format,
        "sequences": sequences,
        "frames": int(sum(s["frames"] for s in sequences)),
        "labeled_frames": int(sum(s["labeled_frames"] for s in sequences)),
        "all_ignore_frames": int(sum(s["all_ignore_frames"] for s in sequences)),
        "points_per_scan": {"mean": float(pts.mean()), "min": int(pts.min()), "max": int(pts.max())},
        "class_histogram": classes,
    }


# ----------------------------------------------------------------------------------------------------------------
# show


# ----------------------------------------------------------------------------------------------------------------
# demo


# The shipped presets (u4d_aug.presets): configs/ of the checkout, or the package data of an installed wheel.
CONFIGS_DIR = configs_root()
# The commands whose work draws progress bars (tqdm): each takes --no-progress, which `u4d demo` passes on.
PROGRESS_COMMANDS = ("simulate", "seg-train", "seg-eval", "seg-predict", "train-diffusion", "train-autoencoder",
                     "generate", "train-extractor", "evaluate", "experiment", "bank-real")  # fmt: skip


def run_demo(args: argparse.Namespace) -> int:
    """`u4d demo`: every stage, each through its own command (`u4d_aug.demo`), then OUT/report.md."""
    import time

    import yaml

    from u4d_aug.demo import demo_experiment, demo_report, demo_steps, sequence_motion
    from u4d_aug.weights import shipped_weights

    real = args.real or Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "semantickitti"
    weights = shipped_weights()
    steps = demo_steps(args.out, args.seed, real, weights)
    verbosity = [flag for flag, level in VERBOSITY_FLAGS.items() if level == args.log_level and flag.startswith("--")]
    print(
        "u4d demo: every stage at toy size (minutes on 2 CPU cores): a small simulated world, nets trained for "
        "seconds to show the training loops run, banks of 64x1024 scans from the shipped nets (weights/), their "
        "generation metrics and the four downstream arms at toy size (one seed, a few steps: it shows the pipeline, "
        "not whether U4D helps; that is `u4d experiment experiment/downstream_10pct`, hours). Ends with OUT/report.md."
    )
    if weights is None:
        print(
            "warning: no shipped nets under weights/ (a wheel install?): the banks come from the seconds-trained nets"
        )
    timings = []
    with run_lock(args.out):  # one demo per output folder; each step locks its own sub-folder too
        atomic_write_text(args.out / "downstream.yaml", yaml.safe_dump(demo_experiment(args.out, args.seed)))
        atomic_save_npy(args.out / "motion_4d.npy", sequence_motion())
        for number, step in enumerate(steps, start=1):
            command = _resume_if_started(step.command)
            if args.no_progress and command[0] in PROGRESS_COMMANDS and "--no-progress" not in command:
                command = [*command, "--no-progress"]
            print(f"\n[{number}/{len(steps)}] {step.title}\n$ u4d {' '.join(command)}", flush=True)
            start = time.perf_counter()
            status = main([*verbosity, *command])
            timings.append((step, time.perf_counter() - start))
            if status != 0:
                print(f"demo stopped at step {number} (exit {status}); re-run to resume", file=sys.stderr)
                return status
        atomic_write_text(args.out / "report.md", demo_report(args.out, timings, weights))
    total = sum(seconds for _, seconds in timings)
    print(f"\ndemo done in {total:.0f} s: outputs in {args.out}; the report: {args.out / 'report.md'}")
    return 0


def _resume_if_started(command: list[str]) -> list[str]:
    """A training step of a re-run demo continues from its newest checkpoint (a finished one just returns)."""
    if command[0] not in ("seg-train", "train-diffusion") or "--out" not in command:
        return command
    out = Path(command[command.index("--out") + 1])
    return [*command, "--resume"] if any((out / "checkpoints").glob("step_*.pt")) else command


def run_show(args: argparse.Namespace) -> int:
    """`u4d show SCAN`: picture, .ply and projection round-trip statistics of one scan."""
    import torch

    from u4d_aug.data.beams import check_beams
    from u4d_aug.data.scan import read_scan
    from u4d_aug.data.sensors import get_sensor
    from u4d_aug.range_view import project, roundtrip_stats, scatter_to_image

    if args.scan.is_dir():
        return _show_sequence(args)
    scan = read_scan(args.scan)
    points, labels = scan.points, scan.labels
    sensor = get_sensor(args.sensor or scan.sensor)
    check_beams(points, sensor, str(args.scan))
    width = sensor.width if args.width is None else args.width
    height = sensor.height
    if width < 3:
        raise InputError(f"--width {width}: a range image needs at least 3 columns")
    if args.png is not None:
        check_output_file(args.png, "picture")
    if args.ply is not None:
        check_output_file(args.ply, ".ply export")
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
    _print_stats(stats, args.json)
    return 0


def _print_stats(stats: dict, as_json: bool) -> None:
    """`u4d show`'s statistics: json, or one `key: value` line each."""
    if as_json:
        print(dumps_json(stats, indent=2))
    else:
        for key, value in stats.items():
            print(f"{key}: {value}")


def _show_sequence(args: argparse.Namespace) -> int:
    """`u4d show SEQUENCE_DIR`: every frame's depth image and a BEV of the frames moved by their poses (--png)."""
    import torch

    from u4d_aug.data.sensors import get_sensor
    from u4d_aug.metrics.temporal import load_kitti_sequence
    from u4d_aug.range_view import project
    from u4d_aug.trajectory import relative_motion

    if args.ply is not None:
        raise InputError(f"{args.scan}: --ply exports one scan; give one of its velodyne/*.bin files")
    check_output_file(args.png, "picture")
    if not (args.scan / "velodyne").is_dir():
        raise InputError(
            f"{args.scan}: no velodyne/ folder (expected a scan file or a SemanticKITTI sequence folder with "
            "velodyne/, poses.txt and calib.txt)"
        )
    scans, poses = load_kitti_sequence(args.scan)
    sensor = get_sensor(args.sensor or "hdl64")
    width = sensor.width if args.width is None else args.width
    depths = [project(torch.from_numpy(s), sensor, sensor.height, width, args.row_mode).depth.numpy() for s in scans]
    relative = relative_motion(poses)[:, :3].astype(np.float64)  # (L, 3) sensor positions in frame 0
    stats = {
        "sequence": str(args.scan),
        "frames": len(scans),
        "points": [int(len(s)) for s in scans],
        "path_m": float(np.linalg.norm(np.diff(relative, axis=0), axis=1).sum()),
        "last_position_m": [round(float(v), 3) for v in relative[-1]],
    }
    if args.png is not None:
        from u4d_aug.viz import plot_sequence

        plot_sequence(args.png, depths, scans, poses, title=f"{args.scan}  {len(scans)} frames, {sensor.name}")
        stats["png"] = str(args.png)
    _print_stats(stats, args.json)
    return 0


_PLY_BYTES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2}
_PLY_BYTES |= {"int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _ply_is_whole(path: Path, count: int) -> bool:
    """Whether a binary .ply of `count` vertices is as long as its header says: header + count x record bytes."""
    header, record = b"", 0
    with open(path, "rb") as f:
        while not header.endswith(b"end_header\n"):
            line = f.readline()
            if not line:
                return False
            header += line
    for words in (line.split() for line in header.decode("ascii", "replace").splitlines()):
        if words[:2] == ["element", "vertex"] and int(words[2]) != count:
            return False
        if words[:1] == ["property"] and len(words) == 3:
            record += _PLY_BYTES.get(words[1], 0)
    return path.stat().st_size == len(header) + count * record


def _write_ply(path: Path, points: np.ndarray, labels: np.ndarray | None) -> None:
    """Export positions, intensity and labels (when known) as .ply attributes with open3d's tensor API, atomically."""
    import contextlib
    import os
    import tempfile

    import open3d as o3d

    from u4d_aug.io import current_umask, make_folder

    cloud = o3d.t.geometry.PointCloud()
    cloud.point.positions = o3d.core.Tensor(np.ascontiguousarray(points[:, :3], dtype=np.float32))  # (N, 3)
    cloud.point.intensity = o3d.core.Tensor(np.ascontiguousarray(points[:, 3:4], dtype=np.float32))  # (N, 1)
    if labels is not None:
        cloud.point.labels = o3d.core.Tensor(np.asarray(labels, dtype=np.int32).reshape(-1, 1))  # (N, 1)
    make_folder(path.parent)
    # open3d picks the format from the name, so the temp file (same folder, for one os.replace) ends in .ply
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".ply", dir=path.parent)
    try:
        os.close(fd)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600; the umask's mode like every other output
        if not o3d.t.io.write_point_cloud(tmp, cloud):
            raise InputError(f"{path}: open3d could not write the .ply file")
        if not _ply_is_whole(Path(tmp), len(points)):  # a full disk makes RPly print errors but report success
            raise InputError(f"{path}: the .ply could not be written whole (disk full?); the file there is kept")
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


if __name__ == "__main__":
    raise SystemExit(main())
