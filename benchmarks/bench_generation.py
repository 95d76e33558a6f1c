"""U4D vs the R2DM-style baseline on the simulated world: Table 1 metrics per seed, mean ± std, real-vs-real floor.

    python benchmarks/bench_generation.py --root data/sim_eval --reference 00-11 --floor 12-23 --num 64 \
        --seeds 0 1 2 --samplers dpmpp2m-sde:20:6 ddpm:32:16 --metrics frd,fpd,jsd,mmd,points,rangejs \
        --out benchmarks/results/generation/generation_64x1024.json
    python benchmarks/bench_generation.py ... --quick            # 8 scans, seeds 0 1, ddpm 8 steps (stage 1: 4)

The nets and extractors default to the shipped ones in weights/, U4D's the one net `weights/u4d.pt` for both stages
(`--net --baseline --extractor-frd --extractor-fpd` take run folders, checkpoints or other weights; `--stage1 --stage2`
a two-net U4D, one net per stage, instead of --net; `--detail nearest|FILE` a cascade: both methods' nets make the
layout, the same detail level the scans, and the floor is projected to the scans' image). Train the generators with
one budget for each method (U4D's budget = its one net's steps, or stage 1 + stage 2, = the baseline's steps x batch
on the same net); the training budgets read from the checkpoints (or the weights' training record) are printed with
the table.
Per sampler setting and seed s: each method generates `--num` scans (sample i uses seed s * 100000 + i) into
WORK/<method>_<sampler tag>_s<s>, scored by `u4d_aug.metrics.evaluate.evaluate` against the reference sequences;
the floor draws `--num` real scans of the `--floor` sequences (disjoint from the reference) with seed s and
scores them the same way, so it is the value a perfect generator would get at this sample size. The json has
`methods.<u4d|baseline|floor>.<metric>.{mean,std,values}` of the first (headline) sampler (the floor also has
`points_projected`: its scans' occupied pixels at the generators' H x W), `ratios` (U4D over the baseline and over
the floor, points per scan over the floor's raw and projected points) and the same per sampler under `samplers`;
`sampler_ratios.<method> <metric> <headline tag>/<tag>`: each method's headline score over its score with every other
setting (the fast sampler against the same nets' 32-step DDPM).
What a segmentor reads, `--metrics teacher,bev_density,roughness`, scores each bank's own scans, not
against the reference: `methods.<name>.teacher_kept_share` / `teacher_building_share` (of the kept pseudo-labels) /
`teacher_class_share` ({class: share}, mean over seeds) of the `--teacher` (`segmentation.teacher_view`),
`bev_points_per_cell` (above-ground points per occupied 0.25 m BEV cell) and `ring_roughness` / `vertical_roughness`
(`u4d_aug.metrics.structure`). Asked for any of them, the floor's scans are also scored after the trip a generated
scan makes (project -> to_image -> unproject at the generators' H x W): `methods.floor_projected`, every metric, and
the ratios `<method>/floor projected <key>`.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from segmentation.teacher_view import load_teacher, teacher_view
from u4d_aug.cascade import NEAREST
from u4d_aug.config import load_config
from u4d_aug.data.datasets import expand_sequences, list_frames
from u4d_aug.data.formats import read_kitti_scan, write_kitti_scan
from u4d_aug.data.sensors import get_sensor
from u4d_aug.errors import InputError
from u4d_aug.generate import GenerateConfig, generate_bank
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text, load_checkpoint
from u4d_aug.metrics.evaluate import METRICS, evaluate, list_scans
from u4d_aug.metrics.structure import depth_roughness, points_per_cell
from u4d_aug.pipeline import load_generator, to_points
from u4d_aug.range_view import project, project_batch, to_image
from u4d_aug.run import newest_checkpoint
from u4d_aug.weights import is_exported

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO / "weights"  # the shipped 64x1024 nets and extractors (weights/README.md)
METHODS = ("u4d", "baseline")
SEED_STRIDE = 100_000
# what a segmentor reads in a scan: the teacher's kept pseudo-labels and their class mix, above-ground points
# per occupied BEV cell, ring / vertical roughness of the range image; scored per bank, not against the reference
STRUCTURE = ("teacher", "bev_density", "roughness")
STRUCTURE_KEYS = {
    "teacher": ("teacher_kept_share", "teacher_building_share", "teacher_class_share"),
    "bev_density": ("bev_points_per_cell",),
    "roughness": ("ring_roughness", "vertical_roughness"),
}


def training_budget(run: Path) -> dict:
    """Steps, batch, wall-clock minutes and net size of a train-diffusion run (its newest checkpoint), checkpoint or
    exported weights (their `trained` record)."""
    path = newest_checkpoint(run) if run.is_dir() else run
    ckpt = load_checkpoint(path, "diffusion checkpoint")
    cfg = ckpt["config"]
    if is_exported(ckpt):
        steps, minutes = ckpt["trained"]["step"], ckpt["trained"].get("elapsed_minutes", 0.0)
    else:
        steps, minutes = ckpt["step"], float(ckpt.get("elapsed", 0.0)) / 60.0
    return {
        "checkpoint": str(path),
        "stage": cfg["diffusion"]["stage"],
        "steps": int(steps),
        "batch_size": cfg["batch_size"],
        "minutes": round(minutes, 2),
        "params": sum(p.numel() for p in load_generator(path).net.parameters()),  # not buffers (ray features)
        "size": [cfg["height"], cfg["width"]],
    }


def floor_bank(root: Path, sequences: list[str], num: int, seed: int, out: Path) -> Path:
    """A 'bank' of `num` real scans of `sequences` drawn with `seed`: symlinks in SemanticKITTI layout."""
    entries = [(seq, frame) for seq in expand_sequences(sequences) for frame in list_frames(root, seq)]
    if len(entries) < num:
        raise InputError(f"--floor {' '.join(sequences)}: {len(entries)} scans, fewer than --num {num}")
    chosen = np.random.default_rng(seed).choice(len(entries), num, replace=False)
    velodyne = out / "sequences" / "00" / "velodyne"
    velodyne.mkdir(parents=True, exist_ok=True)
    for i, index in enumerate(sorted(chosen)):
        seq, frame = entries[index]
        link = velodyne / f"{i:06d}.bin"
        source = (root / "sequences" / seq / "velodyne" / f"{frame}.bin").resolve()
        if not link.is_symlink():
            if link.exists():
                raise InputError(f"{link}: a file this benchmark did not write; pick another --work")
            link.symlink_to(source)
        elif link.resolve() != source:  # another root, sequences or seed wrote this folder
            raise InputError(f"{link}: links {link.resolve()}, not {source}; pick another --work or remove {out}")
    return out


def range_geometry(run: Path) -> dict:
    """Sensor, H, W and row mode a generator was trained at (its config), to project real scans alike."""
    path = newest_checkpoint(run) if run.is_dir() else run
    cfg = load_checkpoint(path, "diffusion checkpoint")["config"]
    return {"sensor": cfg["sensor"], "height": cfg["height"], "width": cfg["width"], "row_mode": cfg["row_mode"]}


def cascade_geometry(layout: dict, detail: str) -> dict:
    """The scans' geometry: the layout nets' own without a cascade, the sensor's width with detail=nearest, a detail
    net's image with detail=FILE (the floor is projected to it)."""
    if not detail:
        return layout
    if detail == NEAREST:
        return {**layout, "width": get_sensor(layout["sensor"]).width}
    return range_geometry(Path(detail))


def projected_points(bank: Path, geometry: dict) -> float:
    """Mean occupied pixels of a bank's scans projected to the generators' range image: the most points a scan
    generated at that resolution can hold (the floor's raw scans hold ~2x more than one image has pixels)."""
    sensor = get_sensor(geometry["sensor"])
    counts = [
        int(
            project(
                read_kitti_scan(path), sensor, geometry["height"], geometry["width"], geometry["row_mode"]
            ).mask.sum()
        )
        for path in sorted(bank.glob("sequences/*/velodyne/*.bin"))
    ]
    if not counts:
        raise InputError(f"{bank}: no scans to project")
    return float(np.mean(counts))


def projected_bank(bank: Path, geometry: dict, out: Path, through=None, width: int | None = None) -> Path:
    """`bank`'s scans as a generator makes its own: projected to its range image, encoded, unprojected at the
    bin-centre rays (`range_view.project` -> `to_image` -> `pipeline.to_points`), one folder in SemanticKITTI layout;
    `through(image (1, 2, H, w), index)` changes the index-th scan's range image before it is unprojected; `width`:
    project at these columns (a cascade's layout) instead of the geometry's, `through` then widens the image."""
    sensor = get_sensor(geometry["sensor"])
    paths = sorted(bank.glob("sequences/*/velodyne/*.bin"))
    if not paths:
        raise InputError(f"{bank}: no scans to project")
    for index, path in enumerate(paths):
        target = out / path.relative_to(bank)
        if not target.exists():
            projection = project(
                read_kitti_scan(path), sensor, geometry["height"], width or geometry["width"], geometry["row_mode"]
            )
            image = to_image(projection, sensor)[None]  # (1, 2, H, W)
            image = image if through is None else through(image, index)
            write_kitti_scan(target, to_points(image, sensor, geometry["row_mode"])[0])
    return out


def autoencoded_bank(bank: Path, autoencoder_path: Path, geometry: dict, out: Path) -> Path:
    """`bank`'s scans through a latent generator's autoencoder (`projected_bank` with the range image encoded to the
    latent and decoded): the best a latent generator with it can do."""
    import torch

    from u4d_aug.autoencoder_stage import load_autoencoder

    autoencoder, ae_cfg = load_autoencoder(autoencoder_path)
    if (ae_cfg.sensor, ae_cfg.height, ae_cfg.width, ae_cfg.row_mode) != (
        geometry["sensor"], geometry["height"], geometry["width"], geometry["row_mode"]
    ):  # fmt: skip
        raise InputError(
            f"{autoencoder_path}: trained on {ae_cfg.sensor} {ae_cfg.height}x{ae_cfg.width} ({ae_cfg.row_mode}) "
            f"images; this score uses {geometry}"
        )

    @torch.no_grad()
    def through(image, index):
        return autoencoder.from_latent(autoencoder.to_latent(image))

    return projected_bank(bank, geometry, out, through)


def layout_nearest_bank(bank: Path, stride: int, geometry: dict, out: Path) -> Path:
    """`bank`'s scans as a cascade with a perfect layout and no detail net makes them: projected at W / s columns,
    each column repeated s times (`cascade.upsample_nearest`, `u4d generate detail=nearest`), unprojected at W."""
    from u4d_aug.cascade import check_stride, upsample_nearest

    low_width = check_stride(geometry["width"], stride, "--layout-nearest")
    return projected_bank(bank, geometry, out, lambda image, index: upsample_nearest(image, stride), low_width)


def detailed_bank(bank: Path, detail_path: Path, geometry: dict, out: Path, seed: int = 0) -> Path:
    """`bank`'s scans as a cascade with a perfect layout makes them: projected at the detail net's W / s columns (the
    layout net's image), completed to W by the detail net (`pipeline.refine`, `u4d generate`'s default sampling, scan
    i drawn with seed + i), unprojected: the best a cascade with this detail net can do."""
    import torch

    from u4d_aug.pipeline import refine

    detail = load_generator(detail_path)
    cfg = detail.config
    if cfg.diffusion.stage != "detail":
        raise InputError(f"{detail_path}: a {cfg.diffusion.stage} net, not a cascade's detail net (stage=detail)")
    if (cfg.sensor, cfg.height, cfg.width, cfg.row_mode) != (
        geometry["sensor"], geometry["height"], geometry["width"], geometry["row_mode"]
    ):  # fmt: skip
        raise InputError(
            f"{detail_path}: completes {cfg.sensor} {cfg.height}x{cfg.width} ({cfg.row_mode}) images; this score uses "
            f"{geometry}"
        )
    if not hasattr(detail.net, "row_mean_detail"):
        raise InputError(
            f"{detail_path}: no stored training mean (the default sampling starts from it); export the net with "
            "`u4d export-weights RUN --out FILE`"
        )

    @torch.no_grad()
    def through(image, index):
        return refine(detail, image, [torch.Generator().manual_seed(seed + index)])["x0"]

    return projected_bank(bank, geometry, out, through, cfg.width // cfg.detail_stride)


def parse_bench_metrics(text: str) -> tuple[str, ...]:
    """'frd,teacher' -> ('frd', 'teacher'): `u4d evaluate`'s metrics and STRUCTURE; one line naming both otherwise."""
    names = tuple(dict.fromkeys(part.strip().lower() for part in text.split(",") if part.strip()))
    table = [name for name in names if name not in STRUCTURE]
    if not names or (table and any(name not in METRICS for name in table)):
        raise InputError(f"--metrics {text!r}: expected a comma-separated subset of {','.join(METRICS + STRUCTURE)}")
    return names


def structure_scores(
    scans: list[np.ndarray], metrics: tuple[str, ...], geometry: dict, teacher: tuple | None = None
) -> dict:
    """The STRUCTURE metrics asked for of scans (N_i, 4): `segmentation.teacher_view.teacher_view` with `teacher`
    = (cfg, net), `structure.points_per_cell`, `structure.depth_roughness` of the scans at `geometry`'s H x W."""
    values: dict = {}
    if "teacher" in metrics:
        cfg, model = teacher
        view = teacher_view(model, cfg, scans)
        values["teacher_kept_share"] = view["kept_share"]
        values["teacher_building_share"] = view["building_share"]
        values["teacher_class_share"] = view["class_share"]
    if "bev_density" in metrics:
        values["bev_points_per_cell"] = points_per_cell(scans)
    if "roughness" in metrics:
        sensor = get_sensor(geometry["sensor"])
        projection = project_batch(scans, sensor, geometry["height"], geometry["width"], geometry["row_mode"])
        rough = depth_roughness(to_image(projection, sensor))  # pooled over the (B, 2, H, W) images
        values["ring_roughness"], values["vertical_roughness"] = rough["ring"], rough["vertical"]
    return values


def score_bank(
    bank: Path,
    reference: Path,
    reference_sequences: list[str] | None,
    metrics: tuple[str, ...],
    extractors: tuple[Path, Path],
    geometry: dict,
    teacher: tuple | None = None,
    max_scans: int | None = None,
) -> dict:
    """One bank's values: `u4d evaluate`'s metrics against the reference scans (`extractors` = FRD, FPD checkpoints)
    and the STRUCTURE metrics of the bank's own scans (`structure_scores`); `max_scans`: the first scans of the bank
    (and of the reference, `evaluate`'s max_scans)."""
    table = tuple(m for m in metrics if m not in STRUCTURE)
    values: dict = {}
    if table:
        result = evaluate(bank, reference, table, max_scans, extractors[0], extractors[1], reference_sequences)
        values = {metric: result["table1"][metric]["value"] for metric in table}
    if any(m in STRUCTURE for m in metrics):
        scans = [read_kitti_scan(path) for _, _, path in list_scans(bank, max_scans)]
        values |= structure_scores(scans, metrics, geometry, teacher)
    return values


class SamplerSpec(NamedTuple):
    """One sampler setting of the comparison: `name:steps:stage1_steps[:grid]`, e.g. dpmpp2m:20:6 or ddpm:32:16."""

    name: str
    steps: int
    stage1_steps: int
    grid: str = "time"

    @property
    def tag(self) -> str:
        grid = "" if self.grid == "time" else f"-{self.grid}"
        return f"{self.name}{grid}_{self.steps}_{self.stage1_steps}"


def parse_sampler(text: str) -> SamplerSpec:
    """'dpmpp2m:20:6' -> SamplerSpec; a one-line error naming the expected form otherwise."""
    parts = text.split(":")
    try:
        if len(parts) not in (3, 4):
            raise ValueError
        spec = SamplerSpec(parts[0], int(parts[1]), int(parts[2]), *(parts[3:] or ["time"]))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected NAME:STEPS:STAGE1_STEPS[:GRID], e.g. dpmpp2m:20:6"
        ) from None
    if spec.steps < 1 or spec.stage1_steps < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: step counts must be >= 1")
    return spec


def generate(method: str, args: argparse.Namespace, spec: SamplerSpec, seed: int, out: Path) -> float:
    """Generate this method's bank for one seed (resumable); returns seconds per newly generated scan."""
    overrides = [f"mode={method}", f"num={args.num}", f"seed={seed * SEED_STRIDE}", f"steps={spec.steps}"]
    overrides += [f"device={args.device}", f"sampler={spec.name}", f"batch_size={args.batch_size}"]
    if spec.grid != "time":
        overrides.append(f"sampler_grid={spec.grid}")
    if method == "u4d":
        if args.net:  # one net for both stages
            overrides += [f"net={args.net}", "stage1=", "stage2="]
        else:
            overrides += [f"stage1={args.stage1}", f"stage2={args.stage2}"]
        overrides.append(f"stage1_steps={spec.stage1_steps}")
        overrides.append(f"stage1_mask_fraction={'null' if args.mask_fraction is None else args.mask_fraction}")
    else:
        overrides.append(f"baseline={args.baseline}")
    if args.detail:  # a cascade: both methods' layouts through the same detail level
        overrides.append(f"detail={args.detail}")
    if args.mean_start_below is None:  # the nets' own x0 at every step (generate's default is the preset's start)
        overrides.append("mean_start_below=null")
    else:  # the nets' training mean image as x0 at vanishing SNR
        overrides.append(f"mean_start_below={args.mean_start_below}")
        overrides += [f"mean_data_root={args.mean_data_root}"] if args.mean_data_root else []
        overrides += [f"mean_probs_root={args.mean_probs_root}"] if args.mean_probs_root else []
    cfg = load_config(GenerateConfig, None, overrides)
    before = len(list((out / "sequences" / "00" / "velodyne").glob("*.bin"))) if out.exists() else 0
    start = time.perf_counter()
    generate_bank(cfg, out, progress=True)
    new = args.num - before
    timing = out / "bench_timing.json"  # a reused bank keeps the speed measured when it was generated
    if new > 0:
        atomic_write_json(timing, {"seconds_per_scan": (time.perf_counter() - start) / new, "scans": new})
    return json.loads(timing.read_text())["seconds_per_scan"] if timing.exists() else float("nan")


def summarise(values: list[float | None]) -> dict:
    """mean, std (sample, 0 for one value), and the per-seed values; None entries are skipped."""
    kept = [v for v in values if v is not None and np.isfinite(v)]
    if not kept:
        return {"mean": None, "std": None, "values": values}
    std = statistics.stdev(kept) if len(kept) > 1 else 0.0
    return {"mean": statistics.fmean(kept), "std": std, "values": values}


def summarise_key(key: str, values: list) -> dict:
    """`summarise` of one row entry; the teacher's class mix (a dict per seed) -> {class: mean share over seeds}."""
    if key == "teacher_class_share":
        return {name: statistics.fmean(v[name] for v in values) for name in values[0]}
    return summarise(values)


def columns(metrics: list[str] | tuple[str, ...]) -> list[str]:
    """The table's columns of the metrics asked for: a STRUCTURE metric's scalar keys, else the metric itself."""
    keys = []
    for metric in metrics:
        keys += [k for k in STRUCTURE_KEYS[metric] if k != "teacher_class_share"] if metric in STRUCTURE else [metric]
    return keys


def ratio(a: dict, b: dict) -> float | None:
    """mean(a) / mean(b), or None when either is missing."""
    if a.get("mean") is None or not b.get("mean"):
        return None
    return a["mean"] / b["mean"]


HEADER = {"frd": "FRD ↓", "fpd": "FPD ↓", "jsd": "JSD ↓", "mmd": "MMD ×10⁴ ↓", "points": "points/scan",
          "rangejs": "range JS ↓", "intensityjs": "intensity JS ↓", "teacher_kept_share": "teacher kept",
          "teacher_building_share": "building of kept", "bev_points_per_cell": "points/BEV cell",
          "ring_roughness": "ring roughness", "vertical_roughness": "vertical roughness"}  # fmt: skip


def table(methods: dict, metrics: list[str]) -> list[str]:
    """Markdown rows = methods, columns = metrics as mean ± std over seeds, then seconds per scan."""
    metrics = columns(metrics)
    lines = ["| method | " + " | ".join(HEADER[m] for m in metrics) + " | s/scan |", "|---" * (len(metrics) + 2) + "|"]
    for name, row in methods.items():
        cells = []
        for metric in metrics:
            s = row[metric]
            cells.append("—" if s["mean"] is None else f"{s['mean']:.4g} ± {s['std']:.2g}")
        speed = row.get("seconds_per_scan", {}).get("mean")
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {'—' if speed is None else f'{speed:.2f}'} |")
    return lines


def to_markdown(result: dict) -> str:
    """One table per sampler setting, the ratios the goals are judged on, and the training budgets."""
    metrics = result["metrics"]
    lines = [
        f"# Generation benchmark: {result['num']} scans per method and seed, seeds {result['seeds']}",
        "",
        f"Reference: sequences {' '.join(result['reference'])} of `{result['root']}`; floor: {result['num']} real "
        f"scans of sequences {' '.join(result['floor_sequences'])} drawn per seed and scored like a generator.",
    ]
    if result.get("mean_start_below") is not None:
        lines.append(f"Mean start: the nets' training mean image as x0 below log-SNR {result['mean_start_below']:g}.")
    for block in result["samplers"].values():
        spec = block["sampler"]
        lines += ["", f"## {spec['name']} {spec['steps']} steps (stage 1: {spec['stage1_steps']}), grid "
                  f"{spec['grid']}", ""]  # fmt: skip
        lines += table(block["methods"], metrics)
        projected = block["methods"]["floor"].get("points_projected", {}).get("mean")
        if projected is not None:
            lines += [
                "",
                f"The floor's scans projected to the generators' range image hold {projected:,.0f} points per scan "
                "(its raw scans: points/scan above), the figure generated scans are compared with.",
            ]
        lines += ["", "| ratio | " + " | ".join(block["ratios"]) + " |", "|---" * (len(block["ratios"]) + 1) + "|"]
        lines.append("| value | " + " | ".join(_fmt_ratio(v) for v in block["ratios"].values()) + " |")
    if result.get("sampler_ratios"):
        lines += [
            "",
            "## Headline sampler over the others (same nets, same seeds)",
            "",
            "| ratio | value |",
            "|---|---|",
        ]
        lines += [f"| {key} | {_fmt_ratio(value)} |" for key, value in result["sampler_ratios"].items()]
    lines += ["", "Training budgets:", ""]
    for name, budget in result["training"].items():
        lines.append(
            f"- {name}: {budget['steps']} steps x batch {budget['batch_size']}, {budget['minutes']} min, "
            f"{budget['params']:,} params, {budget['size'][0]}x{budget['size'][1]}"
        )
    return "\n".join(lines) + "\n"


def sampler_ratios_of(blocks: dict, headline: str, metrics: tuple[str, ...]) -> dict[str, float | None]:
    """Each method's headline-setting score over its score with every other setting, for FRD/FPD/JSD/MMD."""
    ratios = {}
    for tag, block in blocks.items():
        if tag == headline:
            continue
        for name in METHODS:
            for metric in ("frd", "fpd", "jsd", "mmd"):
                if metric in metrics:
                    ratios[f"{name} {metric} {headline}/{tag}"] = ratio(
                        blocks[headline]["methods"][name][metric], block["methods"][name][metric]
                    )
    return ratios


def _fmt_ratio(value: float | None) -> str:
    return "—" if value is None else f"{value:.3f}"


def sampler_block(spec: SamplerSpec, rows: dict, speed: dict, metrics: tuple[str, ...]) -> dict:
    """Summaries of one sampler setting: methods.<name>.<metric>.{mean,std,values} and the goal ratios."""
    methods = {
        name: {key: summarise_key(key, column) for key, column in values.items() if key != "points_projected"}
        | ({"seconds_per_scan": summarise(speed[name])} if name in speed else {})
        for name, values in rows.items()
    }
    ratios = {}
    for metric in ("frd", "fpd", "mmd", "jsd"):
        if metric in metrics:
            ratios[f"u4d/baseline {metric}"] = ratio(methods["u4d"][metric], methods["baseline"][metric])
            ratios[f"u4d/floor {metric}"] = ratio(methods["u4d"][metric], methods["floor"][metric])
    if "points" in metrics:
        for name in METHODS:
            ratios[f"{name} points/floor"] = ratio(methods[name]["points"], methods["floor"]["points"])
        if (
            "points_projected" in rows["floor"]
        ):  # the reference of points per scan: what a real scan holds at the generators' H x W
            methods["floor"]["points_projected"] = summarise(rows["floor"]["points_projected"])
            for name in METHODS:
                ratios[f"{name} points/floor projected"] = ratio(
                    methods[name]["points"], methods["floor"]["points_projected"]
                )
    if "floor_projected" in methods:  # what a segmentor reads, over a real scan's made like a generated one
        for key in columns([m for m in metrics if m in STRUCTURE]):
            for name in METHODS:
                ratios[f"{name}/floor projected {key}"] = ratio(methods[name][key], methods["floor_projected"][key])
    return {"sampler": spec._asdict(), "methods": methods, "ratios": ratios}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="SemanticKITTI root of the reference and floor scans")
    parser.add_argument(
        "--net", type=Path, default=None,
        help="(default: the shipped net weights/u4d.pt) a one-net U4D (train-diffusion stage=u4d: both stages, its "
        "task embedding) run folder, checkpoint or weights",
    )  # fmt: skip
    parser.add_argument(
        "--stage1", type=Path, default=None,
        help="with --stage2, in place of --net: a two-net U4D's stage-1 run folder, checkpoint or weights",
    )  # fmt: skip
    parser.add_argument(
        "--stage2", type=Path, default=None,
        help="with --stage1, in place of --net: a two-net U4D's stage-2 run folder, checkpoint or weights",
    )  # fmt: skip
    parser.add_argument(
        "--baseline",
        type=Path,
        default=WEIGHTS / "baseline.pt",
        help="(default: the shipped net) baseline run folder, checkpoint or weights",
    )
    parser.add_argument("--reference", nargs="+", default=["07"], help="held-out sequences scored against")
    parser.add_argument("--floor", nargs="+", default=["06"], help="other held-out sequences: real-vs-real floor")
    parser.add_argument("--num", type=int, default=64, help="scans per method and seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--samplers", type=parse_sampler, nargs="+", default=[parse_sampler("ddpm:32:8")],
        help="NAME:STEPS:STAGE1_STEPS[:GRID] settings, each scored on its own banks; the first is the headline "
        "(`methods` in the json), e.g. dpmpp2m:20:6 ddpm:32:16",
    )  # fmt: skip
    parser.add_argument(
        "--mask-fraction", type=float, default=None,
        help="U4D: stage 1's mask keeps at most this share of pixels (generate's stage1_mask_fraction; none: no cap)",
    )  # fmt: skip
    parser.add_argument("--batch-size", type=int, default=1, help="scans per sampler call (1: fastest per scan on CPU)")
    parser.add_argument(
        "--mean-start-below", type=float, default=None,
        help="log-SNR under which the samplers take the nets' training mean image as x0 (generate's mean_start_below)",
    )  # fmt: skip
    parser.add_argument(
        "--detail", default="",
        help="a cascade (u4d generate's detail): nearest, or a detail net's weights, after both methods' layout nets",
    )  # fmt: skip
    parser.add_argument("--mean-data-root", default="", help="where the nets' training scans are (mean_data_root)")
    parser.add_argument("--mean-probs-root", default="", help="their probabilities, for stage 1 (mean_probs_root)")
    parser.add_argument(
        "--metrics", default="jsd,mmd,points,rangejs",
        help="subset of frd,fpd,jsd,mmd,points,rangejs,intensityjs and teacher,bev_density,roughness (what a segmentor "
        "reads: the --teacher's kept pseudo-labels and class mix, above-ground points per 0.25 m BEV cell, ring / "
        "vertical roughness; these also score the floor's scans made like generated ones, `floor_projected`)",
    )  # fmt: skip
    parser.add_argument(
        "--teacher", type=Path, default=WEIGHTS / "uncertainty_segmentor.pt",
        help="(default: the shipped segmentor) the teacher of the `teacher` metric: a segmentation checkpoint",
    )  # fmt: skip
    parser.add_argument("--extractor-frd", type=Path, default=WEIGHTS / "extractor_frd.pt", help="(default: shipped)")
    parser.add_argument("--extractor-fpd", type=Path, default=WEIGHTS / "extractor_fpd.pt", help="(default: shipped)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--work", type=Path, default=REPO / "runs" / "bench_generation", help="banks go here")
    parser.add_argument("--quick", action="store_true", help="8 scans, seeds 0 1, ddpm 8 steps (stage 1: 4)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "generation" / "generation.json")
    args = parser.parse_args(argv)
    if args.stage1 is None and args.stage2 is None:
        args.net = args.net or WEIGHTS / "u4d.pt"  # the shipped one-net U4D
    elif args.net is not None or args.stage1 is None or args.stage2 is None:
        parser.error("--stage1 and --stage2 name a two-net U4D together, in place of --net")
    if args.quick:
        args.num, args.seeds, args.samplers = 8, [0, 1], [SamplerSpec("ddpm", 8, 4)]
    try:
        metrics = parse_bench_metrics(args.metrics)
        teacher = load_teacher(args.teacher) if "teacher" in metrics else None
        if args.net:  # one net for both U4D stages
            training = {"u4d": training_budget(args.net)}
        else:
            training = {"u4d stage 1": training_budget(args.stage1), "u4d stage 2": training_budget(args.stage2)}
        training["baseline"] = training_budget(args.baseline)
        geometry = cascade_geometry(range_geometry(args.baseline), args.detail)
        structure = any(m in STRUCTURE for m in metrics)
        floor_rows: dict[str, list] = {}
        projected_rows: dict[str, list] = {}
        blocks = {}
        for spec in args.samplers:
            rows: dict[str, dict[str, list]] = {name: {} for name in METHODS}
            speed: dict[str, list[float]] = {name: [] for name in METHODS}
            for seed in args.seeds:
                start = "" if args.mean_start_below is None else f"_ms{args.mean_start_below:g}"  # other banks
                banks = {name: args.work / f"{name}_{spec.tag}{start}_s{seed}" for name in METHODS}
                for name in METHODS:
                    print(f"{spec.tag} seed {seed}: generating {args.num} scans with {name}", flush=True)
                    speed[name].append(generate(name, args, spec, seed, banks[name]))
                for name, bank in banks.items():
                    values = score(bank, args, metrics, geometry, teacher)
                    for key, value in values.items():
                        rows[name].setdefault(key, []).append(value)
                    print(f"{spec.tag} seed {seed} {name}: {values}", flush=True)
            if not floor_rows:  # the floor does not depend on the sampler: scored once per seed
                for seed in args.seeds:
                    bank = floor_bank(args.root, args.floor, args.num, seed, args.work / f"floor_n{args.num}_s{seed}")
                    values = score(bank, args, metrics, geometry, teacher)
                    if "points" in metrics:
                        values["points_projected"] = projected_points(bank, geometry)
                    for metric in values:
                        floor_rows.setdefault(metric, []).append(values[metric])
                    print(f"floor seed {seed}: {values}", flush=True)
                    if structure:  # the same real scans through the generators' range image
                        out = args.work / f"floor_projected_n{args.num}_s{seed}"
                        values = score(projected_bank(bank, geometry, out), args, metrics, geometry, teacher)
                        for key, value in values.items():
                            projected_rows.setdefault(key, []).append(value)
                        print(f"floor projected seed {seed}: {values}", flush=True)
            reals = {"floor": floor_rows} | ({"floor_projected": projected_rows} if structure else {})
            blocks[spec.tag] = sampler_block(spec, rows | reals, speed, metrics)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    headline = blocks[args.samplers[0].tag]
    sampler_ratios = sampler_ratios_of(blocks, args.samplers[0].tag, metrics)
    result = {
        "benchmark": "generation",
        "command": " ".join(sys.argv),
        "machine": host_info(),
        "root": str(args.root),
        "reference": args.reference,
        "floor_sequences": args.floor,
        "num": args.num,
        "seeds": args.seeds,
        "metrics": list(metrics),
        "mean_start_below": args.mean_start_below,
        "training": training,
        "headline_sampler": headline["sampler"],
        "methods": headline["methods"],
        "ratios": headline["ratios"],
        "sampler_ratios": sampler_ratios,
        "samplers": blocks,
    }
    text = to_markdown(result)
    print(text)
    atomic_write_json(args.out, result)
    atomic_write_text(args.out.with_suffix(".md"), text)
    return 0


def score(
    bank: Path, args: argparse.Namespace, metrics: tuple[str, ...], geometry: dict, teacher: tuple | None
) -> dict:
    """Table-1 values of one bank against the reference sequences and its STRUCTURE values (`score_bank`)."""
    extractors = (args.extractor_frd, args.extractor_fpd)
    return score_bank(bank, args.root, args.reference, metrics, extractors, geometry, teacher)


if __name__ == "__main__":
    sys.exit(main())
