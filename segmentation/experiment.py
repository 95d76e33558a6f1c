"""The augmentation comparison (`u4d experiment CONFIG [key=value ...]`): arms x backbones x seeds, one budget.

Arms: sup-only, MT+LaserMix, MT+LaserMix+R2DM bank, MT+LaserMix+U4D bank. Every run starts from
the same seg-train preset (`base`, e.g. configs/seg/cpu_semi.yaml: label split, step budget, net size) and
changes only mode / bank / backbone / seed, so the arms get the same number of steps on the same labeled
scans (the label split is fixed by data.split_seed; the seed changes initialisation, scan order and mixing).
Each run trains into OUT/runs/ARM/BACKBONE/seedS: skipped once its metrics.json exists, resumed from its
last checkpoint when it was interrupted. An arm whose bank is missing is reported "missing" with the reason,
never with numbers. Writes OUT/results.json, OUT/results.md, OUT/learning_curves_BACKBONE.png (loss and held-out
mIoU against step per arm), OUT/reliability_ARM_BACKBONE.png (bins pooled over seeds) and OUT/paired_BACKBONE.png,
with every arm's mIoU and ECE paired by seed against a reference arm
(sup-only by default): the difference per seed, its mean ± std, the seeds where it is above 0 and a paired t-test;
`contrasts` adds the same comparison for any [arm, reference] pair (an ablation against its parent arm).
`--report-only` trains nothing and reports the finished runs, so arms with different numbers of finished seeds
share one table. With `records_dir`, every finished run also leaves a record (segmentation/records.py) that counts
as that run on a machine without its folder.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from scipy import stats

from segmentation.config import BankConfig, SegTrainConfig
from segmentation.evaluate import evaluate
from segmentation.metrics import ReliabilityBins
from segmentation.plots import plot_arm_curves, plot_paired, plot_reliability
from segmentation.records import (
    CURVE_KEYS,
    PROVENANCE,
    burn_in_digest,
    json_roundtrip,
    log_curves,
    read_record,
    record_path,
    write_record,
)
from segmentation.train import train
from u4d_aug.bank import read_manifest
from u4d_aug.config import (
    config_from_dict,
    config_to_dict,
    load_config,
    read_yaml,
    save_config,
    without_removed_keys,
)
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.errors import InputError
from u4d_aug.io import (
    atomic_torch_save,
    atomic_write_json,
    atomic_write_text,
    load_checkpoint,
    make_folder,
    read_jsonl,
)
from u4d_aug.real_bank import check_real_bank
from u4d_aug.runlock import run_lock
from u4d_aug.validate import check_plain_name

logger = logging.getLogger(__name__)


@dataclass
class ArmConfig:
    """One arm: supervised on the labeled split, or mean teacher + LaserMix with an optional bank."""

    name: str = "sup-only"
    mode: Literal["supervised", "semi"] = "supervised"
    bank: Path | None = None  # SemanticKITTI-layout root of generated scans; None = unlabeled split only
    bank_ratio: float = 0.5  # share of the unlabeled scans drawn from the bank
    # key=value overrides of this arm only, after the experiment's (ablations, e.g. semi.pseudo_threshold=0.75)
    overrides: list[str] = field(default_factory=list)
    # the seeds this arm runs, of the experiment's seeds (an ablation on fewer seeds); None = all of them
    seeds: list[int] | None = None
    # the backbones this arm runs on, of the experiment's (an ablation on one backbone); the arm is left out of the
    # other backbones' tables; None = all of them
    backbones: list[Literal["minkunet", "spvcnn"]] | None = None

    def __post_init__(self) -> None:
        check_plain_name(self.name, "arm name")  # it names the folder OUT/runs/NAME
        if not 0.0 <= self.bank_ratio <= 1.0:
            raise InputError(f"arm {self.name}: bank_ratio must be in [0, 1], got {self.bank_ratio}")
        if self.seeds is not None and not self.seeds:
            raise InputError(f"arm {self.name}: seeds must list at least one seed (or be left out for all), got []")
        if self.backbones is not None and not self.backbones:
            raise InputError(f"arm {self.name}: backbones must name at least one (or be left out for all), got []")


def default_arms() -> list[ArmConfig]:
    """The four arms of the downstream comparison (bank paths: where `u4d generate` writes the two banks)."""
    return [
        ArmConfig("sup-only", "supervised"),
        ArmConfig("mt-lasermix", "semi"),
        ArmConfig("mt-lasermix-r2dm", "semi", Path("banks/r2dm")),
        ArmConfig("mt-lasermix-u4d", "semi", Path("banks/u4d")),
    ]


@dataclass
class ExperimentConfig:
    """Arms x backbones x seeds on one seg-train preset; `overrides` apply to every run (key=value)."""

    base: Path = Path("configs/seg/cpu_semi.yaml")
    overrides: list[str] = field(default_factory=list)
    arms: list[ArmConfig] = field(default_factory=default_arms)
    backbones: list[Literal["minkunet", "spvcnn"]] = field(default_factory=lambda: ["minkunet", "spvcnn"])
    # key=value overrides of one backbone's runs, after the experiment's and the arm's: a recipe key one backbone
    # cannot take (spvcnn: [loss.level=point], its head reads points)
    backbone_overrides: dict[str, list[str]] = field(default_factory=dict)
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    out_dir: Path = Path("runs/experiment")
    # a run whose first semi.burn_in_steps steps equal another run's (same backbone, seed and config but for the mode
    # and the semi keys read after burn-in) starts from that run's OUT/burn_in.pt instead of repeating them
    share_burn_in: bool = True
    # the arm every other arm is paired with, seed by seed, in results.md; None = the first supervised arm
    reference_arm: str | None = None
    # further seed-paired comparisons [arm, reference] between any two arms (an ablation against its parent arm,
    # a treatment against its own control), reported as "arm - reference" beside the comparisons with reference_arm
    contrasts: list[tuple[str, str]] = field(default_factory=list)
    # evaluate each finished run's model.pt once on every labelled scan of its data.val_sequences (RUN/eval_full.json,
    # reused) and report those figures instead of the periodic evaluation's (data.val_max_scans scans)
    final_eval: bool = False
    # where each finished run's record is kept (segmentation/records.py: its figures, curves and host as json, e.g. a
    # folder in the repository): a run with a record of the same recipe counts as finished on any machine, and the
    # tables are built from run folders and records together; None = run folders only
    records_dir: Path | None = None

    def __post_init__(self) -> None:
        names = [arm.name for arm in self.arms]
        if not names or len(set(names)) != len(names):
            raise ValueError(f"arms must be a non-empty list with distinct names; got {names}")
        if self.reference_arm is not None and self.reference_arm not in names:
            raise ValueError(f"reference_arm {self.reference_arm!r} is not one of the arms {names}")
        for i, pair in enumerate(self.contrasts):
            if len(pair) != 2 or pair[0] == pair[1]:
                raise ValueError(f"contrasts[{i}] must be [arm, reference] with two different arms; got {list(pair)}")
            unknown = [name for name in pair if name not in names]
            if unknown:
                raise ValueError(f"contrasts[{i}] names {unknown[0]!r}, which is not one of the arms {names}")
        if not self.backbones or not self.seeds:
            raise ValueError("backbones and seeds must not be empty")
        for name, items in self.backbone_overrides.items():
            if name not in ("minkunet", "spvcnn"):
                raise ValueError(f"backbone_overrides: {name!r} is not a backbone (minkunet, spvcnn)")
            if not isinstance(items, list) or not all(isinstance(item, str) and "=" in item for item in items):
                raise ValueError(f"backbone_overrides.{name}: expected a list of key=value strings, got {items!r}")


def bank_problem(arm: ArmConfig) -> str | None:
    """Why an arm's bank cannot be used (missing folder, no scans), or None."""
    if arm.bank is None:
        return None
    if not Path(arm.bank).is_dir():
        return f"bank {arm.bank} not found (generate it first)"
    try:
        count = len(ScanDataset(arm.bank, None))
    except InputError as exc:
        return f"bank {arm.bank} unusable: {exc}"
    if count == 0:
        return f"bank {arm.bank} holds no scan"
    manifest = read_manifest(arm.bank)  # None for a bank written by other tools
    if manifest is not None and manifest.get("complete") is False:
        return f"bank {arm.bank} is incomplete ({count} scans so far): its `u4d generate` has not finished"
    return None


def check_ceiling_banks(cfg: ExperimentConfig) -> None:
    """Refuse an arm whose bank of real scans (`u4d bank-real`) shares places with the experiment's training
    (labelled and unlabelled) or held-out sequences: a ceiling must add scans of places the runs never see."""
    for arm in cfg.arms:
        if arm.bank is None or bank_problem(arm) is not None:
            continue
        run = run_config(cfg, arm, cfg.backbones[0], cfg.seeds[0])
        splits = {"data.train_sequences": run.data.train_sequences, "data.val_sequences": run.data.val_sequences}
        check_real_bank(arm.bank, Path(run.data.root), {k: v for k, v in splits.items() if v})


def run_config(cfg: ExperimentConfig, arm: ArmConfig, backbone: str, seed: int) -> SegTrainConfig:
    """The seg-train config of one run: the base preset + the experiment's, the arm's and the backbone's overrides +
    backbone / seed."""
    out = cfg.out_dir / "runs" / arm.name / backbone / f"seed{seed}"
    extra = cfg.backbone_overrides.get(backbone, [])
    overrides = [*cfg.overrides, *arm.overrides, *extra, f"model.name={backbone}", f"seed={seed}"]
    run = load_config(SegTrainConfig, cfg.base, overrides)
    run.mode = arm.mode
    run.out_dir = out
    run.semi.banks = [BankConfig(Path(arm.bank), arm.bank_ratio)] if arm.bank is not None else []
    return run


def burn_in_signature(run: SegTrainConfig) -> str | None:
    """What fixes a run's first semi.burn_in_steps steps, as text; None when it has none to share.

    The config without mode, out_dir and the semi keys that act only after burn-in: a supervised run and a
    mean-teacher run with the same signature take the same first steps bit for bit (tests/segmentation/test_semi.py),
    the teacher of the mean-teacher run being a copy of the student until then.
    """
    if run.semi.burn_in_steps <= 0:
        return None
    fixed = config_to_dict(run)
    for key in ("mode", "out_dir"):
        fixed.pop(key)
    fixed["semi"] = {"burn_in_steps": run.semi.burn_in_steps}
    return json.dumps(fixed, sort_keys=True, default=str)


def start_from_burn_in(run: SegTrainConfig, donors: list[SegTrainConfig]) -> Path | None:
    """Seed a run that has not started with a donor's OUT/burn_in.pt (same signature); returns the donor file.

    The donor's checkpoint becomes the run's step-B checkpoint (its teacher = the student, as the burn-in makes
    it) and the donor's log records up to step B its log, so the run resumes at step B.
    """
    out = Path(run.out_dir)
    signature = burn_in_signature(run)
    if signature is None or (out / "metrics.json").is_file() or any((out / "checkpoints").glob("step_*.pt")):
        return None
    for donor in donors:
        source = Path(donor.out_dir) / "burn_in.pt"
        if Path(donor.out_dir) == out or not source.is_file() or burn_in_signature(donor) != signature:
            continue
        state = load_checkpoint(source, "burn-in checkpoint")
        steps = run.semi.burn_in_steps
        if int(state.get("step", -1)) != steps:
            continue
        if state.get("ema") is None:  # a supervised donor: the teacher starts as a copy of the student
            state["ema"] = {key: value.clone() for key, value in state["model"].items()}
        state["config"] = config_to_dict(run)
        atomic_torch_save(out / "checkpoints" / f"step_{steps:07d}.pt", state)
        records = [r for r in read_jsonl(Path(donor.out_dir) / "log.jsonl") if r.get("step", 0) <= steps]
        atomic_write_text(out / "log.jsonl", "".join(json.dumps(r) + "\n" for r in records))
        return source
    return None


def donors_on_disk(out_dir: Path) -> list[SegTrainConfig]:
    """Runs under OUT/runs/ that hold a burn_in.pt, read from their config.yaml: burn-in donors, whether this
    `u4d experiment` process trained them or another one did (e.g. one restricted to other arms, on another core).

    A run saved before a key was removed still donates when that key held its "off" value; one whose burn-in used a
    since-removed setting does not (its first steps are no run's of today)."""
    donors = []
    for path in sorted(Path(out_dir).glob("runs/*/*/*/config.yaml")):
        if not (path.parent / "burn_in.pt").is_file():
            continue
        data, acted = without_removed_keys(SegTrainConfig, read_yaml(path))
        if acted:
            logger.info("%s: not a burn-in donor, trained with the since-removed %s", path, ", ".join(acted))
            continue
        donors.append(config_from_dict(SegTrainConfig, data, source=str(path)))
    return donors


def burn_in_weights(run: SegTrainConfig, out_dir: Path) -> str | None:
    """Digest of the burn-in a finished run started from: its own OUT/burn_in.pt or its donor's (same signature)."""
    signature = burn_in_signature(run)
    if signature is None:
        return None
    candidates = [Path(run.out_dir) / "burn_in.pt"]
    candidates += [Path(d.out_dir) / "burn_in.pt" for d in donors_on_disk(out_dir) if burn_in_signature(d) == signature]
    found = next((path for path in candidates if path.is_file()), None)
    return None if found is None else burn_in_digest(found)


def full_evaluation(run: SegTrainConfig, progress: bool) -> dict:
    """The run's model.pt on every labelled scan of its validation sequences; written once to RUN/eval_full.json."""
    path = Path(run.out_dir) / "eval_full.json"
    if not path.is_file():
        summary = evaluate(
            Path(run.out_dir) / "model.pt", run.data.root, run.data.val_sequences, device=run.device, progress=progress
        )
        atomic_write_json(path, summary)
    return json.loads(path.read_text())


def run_metrics(run: SegTrainConfig, final_eval: bool, progress: bool) -> dict | None:
    """What the tables report for one finished run (None when unfinished): metrics.json or, with final_eval, the
    full evaluation (then "periodic_miou" keeps metrics.json's), plus the wall-clock seconds."""
    metrics = finished_metrics(Path(run.out_dir))
    if metrics is None or not final_eval:
        return metrics
    keys = ("miou", "miou_present", "iou", "ece_per_scan", "ece_pooled", "bins", "num_scans", "num_points", "bands")
    full = full_evaluation(run, progress)
    return {**metrics, "periodic_miou": metrics["miou"], **{key: full.get(key) for key in keys}}


def run_one(run: SegTrainConfig, progress: bool) -> None:
    """Train (or resume, or skip when finished) one run: afterwards RUN/metrics.json exists.

    A run interrupted before its first checkpoint starts again from step 0 (`u4d_aug.runfolder`).
    """
    if not (Path(run.out_dir) / "metrics.json").is_file():
        train(run, resume="last", progress=progress)


def finished_metrics(out: Path) -> dict | None:
    """A finished run's metrics.json plus its wall-clock seconds (from its log), or None when it has not finished."""
    metrics_path = out / "metrics.json"
    if not metrics_path.is_file():
        return None
    metrics = json.loads(metrics_path.read_text())
    times = [r["time"] for r in read_jsonl(out / "log.jsonl") if "time" in r] if (out / "log.jsonl").is_file() else []
    metrics["wall_clock_s"] = max(times) if times else None  # training time incl. resumes, from the log
    return metrics


def mean_std(values: list[float | None]) -> dict:
    """{"mean", "std" (sample, ddof 1; 0 for one value), "n"} over the non-null values."""
    kept = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not kept:
        return {"mean": None, "std": None, "n": 0}
    std = float(np.std(kept, ddof=1)) if len(kept) > 1 else 0.0
    return {"mean": float(np.mean(kept)), "std": std, "n": len(kept)}


def bins_from_dict(data: dict) -> ReliabilityBins:
    """Rebuild pooled reliability bins from `ReliabilityBins.to_dict()` (for pooling over seeds)."""
    count = np.asarray(data["count"], dtype=np.int64)
    confidence = np.nan_to_num(np.asarray(data["confidence"], dtype=np.float64))
    accuracy = np.nan_to_num(np.asarray(data["accuracy"], dtype=np.float64))
    return ReliabilityBins(count, confidence * count, accuracy * count, int(data["total"]))


def mean_text(stat: dict | None, scale: float = 1.0, digits: int = 2, signed: bool = False) -> str:
    """A `mean_std` stat times `scale`: '46.59 ± 1.89', '47.10 (1 seed)' where one value has no spread, or 'n/a'."""
    if stat is None or stat.get("mean") is None:
        return "n/a"
    mean = f"{scale * stat['mean']:{'+' if signed else ''}.{digits}f}"
    return f"{mean} (1 seed)" if stat.get("n") == 1 else f"{mean} ± {scale * stat['std']:.{digits}f}"


MAX_SEEDS_ESTIMATE = 200  # seeds_needed gives up beyond this


def paired_differences(reference: dict[int, float], other: dict[int, float]) -> dict:
    """Seed-paired other - reference (seeds finished in both): per seed, mean ± std, seeds above 0, paired t-test p,
    the 95 % confidence interval of the mean difference and `seeds_needed` (see below).

    p is two-sided (scipy.stats.ttest_rel); p and the interval are None with fewer than 2 pairs, p also when every
    difference is the same.
    """
    seeds = sorted(set(reference) & set(other))
    diffs = [float(other[s] - reference[s]) for s in seeds]
    summary = {"seeds": seeds, "per_seed": diffs, **mean_std(diffs), "above": sum(d > 0 for d in diffs), "p": None}
    summary["ci95"], summary["seeds_needed"] = None, None
    if len(diffs) > 1:
        half = float(stats.t.ppf(0.975, len(diffs) - 1)) * summary["std"] / math.sqrt(len(diffs))
        summary["ci95"] = [summary["mean"] - half, summary["mean"] + half]
        summary["seeds_needed"] = seeds_needed(summary["mean"], summary["std"])
    if len(diffs) > 1 and np.ptp(diffs) > 0:
        summary["p"] = float(stats.ttest_rel([other[s] for s in seeds], [reference[s] for s in seeds]).pvalue)
    return summary


def seeds_needed(mean: float, std: float) -> int | None:
    """Paired seeds at which a difference of this mean and seed-to-seed std reaches p < 0.05 (two-sided t-test):
    the smallest n >= 2 with t_0.975(n-1)·std/√n < |mean|; None when the mean is 0 or it needs over 200 seeds."""
    if mean == 0:
        return None
    if std == 0:
        return 2
    for n in range(2, MAX_SEEDS_ESTIMATE + 1):
        if float(stats.t.ppf(0.975, n - 1)) * std / math.sqrt(n) < abs(mean):
            return n
    return None


def paired_arms(reference: dict, other: dict) -> dict:
    """Seed-paired mIoU, ECE-per-scan and per-class IoU differences other - reference of two finished arm entries."""
    paired = {"arm": reference["arm"]}
    for key in ("miou", "ece_per_scan"):
        values = [{r["seed"]: r[key] for r in entry["runs"] if r.get(key) is not None} for entry in (reference, other)]
        paired[key] = paired_differences(*values)
    classes = list(
        dict.fromkeys(c for entry in (reference, other) for r in entry["runs"] for c in (r.get("iou") or {}))
    )
    paired["iou"] = {}
    for name in classes:
        values = [
            {r["seed"]: r["iou"][name] for r in entry["runs"] if (r.get("iou") or {}).get(name) is not None}
            for entry in (reference, other)
        ]
        paired["iou"][name] = paired_differences(*values)
    paired["bands"] = {}
    for band in band_names(reference["runs"] + other["runs"]):
        values = [{r["seed"]: band_miou(r, band) for r in entry["runs"] if band_miou(r, band) is not None}
                  for entry in (reference, other)]  # fmt: skip
        paired["bands"][band] = paired_differences(*values)
    return paired


def band_label(band: dict) -> str:
    """'0-10 m', ..., '>= 50 m' for a distance band of `segmentation.evaluate`."""
    low, high = band["range"]
    return f"{low:g}-{high:g} m" if high is not None else f">= {low:g} m"


def band_names(runs: list[dict]) -> list[str]:
    """The distance bands the runs were evaluated in (full evaluation), near to far."""
    return list(dict.fromkeys(band_label(b) for r in runs for b in (r.get("bands") or [])))


def band_miou(run: dict, name: str) -> float | None:
    """A run's mIoU in one distance band (None when not evaluated there)."""
    return next((b["miou"] for b in (run.get("bands") or []) if band_label(b) == name), None)


def compare_to_reference(arms: list[dict], reference: str) -> None:
    """Add "vs_reference" (paired mIoU and ECE-per-scan differences) to every finished arm but the reference."""
    for backbone in dict.fromkeys(e["backbone"] for e in arms):
        ref = next((e for e in arms if e["arm"] == reference and e["backbone"] == backbone and e.get("runs")), None)
        if ref is None:
            continue
        for e in arms:
            if e is ref or e["backbone"] != backbone or not e.get("runs"):
                continue
            e["vs_reference"] = paired_arms(ref, e)


def contrast_arms(arms: list[dict], contrasts: list[tuple[str, str]]) -> list[dict]:
    """Per backbone and [arm, reference] pair with both finished: {"arm", "reference", "backbone", "miou", ...}."""
    rows = []
    for backbone in dict.fromkeys(e["backbone"] for e in arms):
        finished = {e["arm"]: e for e in arms if e["backbone"] == backbone and e.get("runs")}
        for name, reference in contrasts:
            if name in finished and reference in finished:
                paired = paired_arms(finished[reference], finished[name])
                rows.append({**paired, "arm": name, "reference": reference, "backbone": backbone})
    return rows


def run_experiment_config(
    cfg: ExperimentConfig, progress: bool = True, report_only: bool = False, train_arms: Sequence[str] | None = None
) -> dict:
    """Every run (skipping finished ones), then results.json, results.md and the reliability PNGs.

    report_only: train nothing; report the runs that have finished (an arm with some seeds finished is "partial"),
    evaluating those whose full evaluation is missing when final_eval is set. train_arms: train only these arms
    (names of cfg.arms), report the others as report_only does.
    """
    _check_train_arms(cfg, report_only, train_arms)
    check_ceiling_banks(cfg)
    out = make_folder(cfg.out_dir)
    save_config(cfg, out / "experiment.yaml")
    results: dict = {"config": config_to_dict(cfg), "arms": []}
    for arm in cfg.arms:
        train = not report_only and (train_arms is None or arm.name in train_arms)
        problem = bank_problem(arm)
        for backbone in cfg.backbones:
            if arm.backbones is not None and backbone not in arm.backbones:
                continue  # not part of this backbone's table
            results["arms"].append(_arm_entry(cfg, arm, backbone, out, train, problem, progress))
    supervised = [arm.name for arm in cfg.arms if arm.mode == "supervised"]
    reference = cfg.reference_arm or (supervised[0] if supervised else None)
    if reference is not None:
        compare_to_reference(results["arms"], reference)
        _plot_paired_arms(results, cfg.backbones, out, reference)
    results["contrasts"] = contrast_arms(results["arms"], [tuple(pair) for pair in cfg.contrasts])
    _plot_learning_curves(results, cfg.backbones, out)
    atomic_write_json(out / "results.json", results)
    atomic_write_text(out / "results.md", results_markdown(results))
    return results


def _check_train_arms(cfg: ExperimentConfig, report_only: bool, train_arms: Sequence[str] | None) -> None:
    """Refuse --arms naming an arm the experiment does not have, or one to train whose bank cannot be used."""
    names = [arm.name for arm in cfg.arms]
    unknown = [name for name in train_arms or () if name not in names]
    if unknown:
        raise InputError(f"--arms: {unknown[0]!r} is not an arm of the experiment; its arms are {names}")
    for arm in cfg.arms:
        problem = bank_problem(arm)
        if train_arms is not None and not report_only and arm.name in train_arms and problem is not None:
            raise InputError(f"--arms: arm {arm.name!r} cannot run: {problem}")


def _arm_entry(
    cfg: ExperimentConfig, arm: ArmConfig, backbone: str, out: Path, train: bool, problem: str | None, progress: bool
) -> dict:
    """One arm on one backbone: its runs (trained here when `train` and its bank is usable), their mean ± std and
    pooled reliability diagram, or the status "missing" / "not run" with the reason."""
    entry: dict = {
        "arm": arm.name,
        "mode": arm.mode,
        "backbone": backbone,
        "bank": None if arm.bank is None else str(arm.bank),
        "overrides": list(arm.overrides),
    }
    seeds = [seed for seed in cfg.seeds if arm.seeds is None or seed in arm.seeds]
    runs = []
    for seed in seeds:
        run = _seed_run(cfg, arm, backbone, seed, out, train, problem, progress)
        if run is not None:
            runs.append(run)
    if not runs and problem is not None:  # nothing recorded and nothing can run: never numbers
        entry.update(status="missing", reason=problem)
        logger.warning("%s / %s: missing (%s)", arm.name, backbone, problem)
        return entry
    if not runs:
        reason = "no finished run" if seeds else f"its seeds {arm.seeds} are not among the seeds {cfg.seeds}"
        entry.update(status="not run", reason=reason)
        return entry
    status = "done" if len(runs) == len(seeds) else "partial"
    entry.update(status=status, **aggregate(runs))
    entry["runs"] = [{k: v for k, v in r.items() if k != "bins"} for r in runs]
    pooled = _pooled_bins(runs)
    if pooled is not None:
        png = out / f"reliability_{arm.name}_{backbone}.png"
        plot_reliability(pooled, png, title=f"{arm.name} / {backbone} ({len(runs)} seeds)")
        entry["reliability_png"] = png.name
    return entry


def _pooled_bins(runs: list[dict]) -> ReliabilityBins | None:
    """The reliability bins of the runs that have them, pooled (None when none has)."""
    pooled = None
    for r in runs:
        if r.get("bins"):
            bins = bins_from_dict(r["bins"])
            pooled = bins if pooled is None else pooled + bins
    return pooled


def _seed_run(
    cfg: ExperimentConfig,
    arm: ArmConfig,
    backbone: str,
    seed: int,
    out: Path,
    train: bool,
    problem: str | None,
    progress: bool,
) -> dict | None:
    """One seed of an arm: trained (or resumed) here when it may be, then its figures and curves from its folder or
    its record (a finished run leaves or refreshes its record); None when it has not finished."""
    run = run_config(cfg, arm, backbone, seed)
    t0 = time.perf_counter()
    path = None if cfg.records_dir is None else record_path(cfg.records_dir, arm.name, backbone, seed)
    record = None if path is None else read_record(path, run)
    trained = train and record is None and problem is None
    if trained:
        logger.info("%s / %s / seed %d -> %s", arm.name, backbone, seed, run.out_dir)
        with run_lock(run.out_dir):  # per run folder: other processes may train other arms or seeds
            donor = start_from_burn_in(run, donors_on_disk(out)) if cfg.share_burn_in else None
            if donor is not None:
                logger.info("  starts at step %d from %s (the same burn-in)", run.semi.burn_in_steps, donor)
            run_one(run, progress)
    metrics = run_metrics(run, cfg.final_eval, progress)
    if metrics is not None:
        curves = log_curves(Path(run.out_dir) / "log.jsonl")
        if path is not None and (record is None or record["metrics"] != json_roundtrip(metrics)):
            write_record(path, run, metrics, curves, burn_in_weights(run, out))
            record = read_record(path, run)
    elif record is not None:
        metrics, curves = record["metrics"], record["curves"]
    else:  # not trained here and not finished
        return None
    source = str(run.out_dir) if (Path(run.out_dir) / "metrics.json").is_file() else str(path)
    # where it ran, from which burn-in, on which bank scans: known for runs with a record
    provenance = {key: record.get(key) for key in PROVENANCE} if record is not None else {}
    if trained:
        logger.info("  done in %.1f s (mIoU %s)", time.perf_counter() - t0, metrics.get("miou"))
    return {"seed": seed, "out_dir": source, "curves": curves, **provenance, **metrics}


def _plot_paired_arms(results: dict, backbones: list[str], out: Path, reference: str) -> None:
    """OUT/paired_BACKBONE.png of each backbone with arms paired against the reference (named in `results`)."""
    for backbone in backbones:
        paired = {
            e["arm"]: e["vs_reference"] for e in results["arms"] if e["backbone"] == backbone and "vs_reference" in e
        }
        if paired:
            png = out / f"paired_{backbone}.png"
            plot_paired(paired, png, reference)
            results[f"paired_png_{backbone}"] = png.name


def _plot_learning_curves(results: dict, backbones: list[str], out: Path) -> None:
    """OUT/learning_curves_BACKBONE.png of each backbone with finished arms (named in `results`)."""
    for backbone in backbones:
        curves = {
            e["arm"]: run_curves(e["runs"]) for e in results["arms"] if e["backbone"] == backbone and e.get("runs")
        }
        if curves:
            png = out / f"learning_curves_{backbone}.png"
            plot_arm_curves(curves, png)
            results[f"learning_curves_png_{backbone}"] = png.name


def run_curves(runs: list[dict]) -> dict[str, list[list[tuple[float, float]]]]:
    """Per seed, (step, value) of the training loss and the periodic held-out mIoU (each run's log or record)."""
    return {
        key: [[(float(step), float(value)) for step, value in run["curves"].get(key, [])] for run in runs]
        for key in CURVE_KEYS
    }


def aggregate(runs: list[dict]) -> dict:
    """mean ± std over seeds of mIoU, both ECEs, wall-clock and per-class IoU."""
    classes = list(dict.fromkeys(name for r in runs for name in (r.get("iou") or {})))  # first-seen order
    return {
        "miou": mean_std([r.get("miou") for r in runs]),
        "miou_present": mean_std([r.get("miou_present") for r in runs]),  # over classes with GT points
        "ece_per_scan": mean_std([r.get("ece_per_scan") for r in runs]),
        "ece_pooled": mean_std([r.get("ece_pooled") for r in runs]),
        "wall_clock_s": mean_std([r.get("wall_clock_s") for r in runs]),
        "iou": {name: mean_std([(r.get("iou") or {}).get(name) for r in runs]) for name in classes},
        "bands": {name: mean_std([band_miou(r, name) for r in runs]) for name in band_names(runs)},
    }


def starred(stat: dict | None) -> str:
    """A paired mean difference in points, '*' when its 95 % confidence interval excludes 0."""
    if stat is None or stat["mean"] is None:
        return "n/a"
    ci = stat.get("ci95")
    return f"{100 * stat['mean']:+.1f}" + ("*" if ci is not None and (ci[0] > 0 or ci[1] < 0) else "")


def results_markdown(results: dict) -> str:
    """The results table (percentages, mean ± std over seeds) and per-class IoU of the finished arms."""
    done = [e for e in results["arms"] if e["status"] in ("done", "partial")]
    lines = _arms_table(results)
    lines += _paired_table(results)
    lines += _contrasts_tables(results)
    lines += _bands_tables(results, done)
    lines += _classes_table(done)
    return "\n".join(lines) + "\n"


# the columns `_paired_cells` fills
_PAIRED_COLUMNS = (
    "mIoU difference per seed | mean ± std | 95 % CI | seeds won | p | seeds for p < 0.05 | ECE per scan diff. |"
)


def _pct(stat: dict) -> str:
    """A `mean_std` stat of a fraction in %."""
    return mean_text(stat, scale=100)


def _signed(stat: dict) -> str:
    """A `mean_std` stat of a difference of fractions in signed points."""
    return mean_text(stat, scale=100, signed=True)


def _paired_cells(paired: dict) -> str:
    """The `_PAIRED_COLUMNS` cells of a seed-paired comparison (`paired_arms`), in points."""
    miou, ece = paired["miou"], paired["ece_per_scan"]
    per_seed = ", ".join(f"{100 * d:+.2f}" for d in miou["per_seed"])
    p_text = "n/a" if miou["p"] is None else f"{miou['p']:.2g}"
    ci = miou.get("ci95")
    ci_text = "n/a" if ci is None else f"[{100 * ci[0]:+.2f}, {100 * ci[1]:+.2f}]"
    needed = miou.get("seeds_needed")
    needed_text = "n/a" if ci is None else (f"{needed}" if needed is not None else f"> {MAX_SEEDS_ESTIMATE}")
    return (
        f"{per_seed} | {_signed(miou)} | {ci_text} | {miou['above']} of {miou['n']} | {p_text} | {needed_text} | "
        f"{_signed(ece)}"
    )


def _contrast_row(row: dict, cells: str) -> str:
    """A table row of a contrast (`contrast_arms`): arm, reference, backbone, then `cells`."""
    return f"| {row['arm']} | {row['reference']} | {row['backbone']} | {cells} |"


def _arms_table(results: dict) -> list[str]:
    """The title, what the figures are, and one row per arm and backbone (mean ± std over its seeds, or its status)."""
    scans = sorted({r.get("num_scans") for e in results["arms"] for r in e.get("runs", [])} - {None})
    scans_text = "/".join(str(n) for n in scans) or "?"
    if results["config"].get("final_eval"):
        evaluated = f"final evaluation of each model.pt on all {scans_text} labelled validation scans"
    else:
        evaluated = f"the last periodic evaluation ({scans_text} validation scans)"
    lines = [
        "# Augmentation comparison",
        "",
        "mean ± std over seeds, in %: mIoU over all classes and over the classes with ground-truth points (present);"
        " ECE per scan = mean of per-scan ECEs, pooled = over all points.",
        f"Figures: {evaluated}.",
        "",
        "| arm | backbone | status | seeds | mIoU | mIoU present | ECE per scan | ECE pooled | wall-clock per run s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for e in results["arms"]:
        if e["status"] not in ("done", "partial"):
            lines.append(f"| {e['arm']} | {e['backbone']} | {e['status']}: {e['reason']} | - | - | - | - | - | - |")
            continue
        seeds = ", ".join(str(r["seed"]) for r in e["runs"])
        lines.append(
            f"| {e['arm']} | {e['backbone']} | {e['status']} | {seeds} | {_pct(e['miou'])} | {_pct(e['miou_present'])} "
            f"| {_pct(e['ece_per_scan'])} | {_pct(e['ece_pooled'])} | {mean_text(e['wall_clock_s'], digits=1)} |"
        )
    return lines


def _paired_table(results: dict) -> list[str]:
    """Every arm paired by seed against the reference arm (none when no arm was)."""
    paired = [e for e in results["arms"] if "vs_reference" in e]
    if not paired:
        return []
    lines = [
        "",
        f"## Paired by seed against {paired[0]['vs_reference']['arm']} (points)",
        "",
        "arm - reference on the seeds both finished; p: two-sided paired t-test (n/a below 2 seeds); "
        "seeds for p < 0.05: paired seeds at which the same mean and spread would reach it.",
        "",
        "| arm | backbone | seeds | " + _PAIRED_COLUMNS,
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in paired:
        seeds = len(e["vs_reference"]["miou"]["seeds"])
        lines.append(f"| {e['arm']} | {e['backbone']} | {seeds} | " + _paired_cells(e["vs_reference"]) + " |")
    return lines


def _contrasts_tables(results: dict) -> list[str]:
    """The contrasts (`ExperimentConfig.contrasts`) paired by seed, then their per-class IoU differences."""
    contrasts = results.get("contrasts")
    if not contrasts:
        return []
    lines = [
        "",
        "## Contrasts (points)",
        "",
        "arm - reference, paired by seed on the seeds both finished; p: two-sided paired t-test.",
        "",
        "| arm | reference | backbone | " + _PAIRED_COLUMNS,
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [_contrast_row(c, _paired_cells(c)) for c in contrasts]
    classes = list(dict.fromkeys(c for row in contrasts for c in row.get("iou", {})))
    lines += [
        "",
        "## Where the differences come from: per-class IoU, paired by seed (points)",
        "",
        "mean difference over the paired seeds; * where its 95 % confidence interval excludes 0.",
        "",
        "| arm | reference | backbone | " + " | ".join(classes) + " |",
        "|---|---|---|" + "---|" * len(classes),
    ]
    for row in contrasts:
        lines.append(_contrast_row(row, " | ".join(starred(row.get("iou", {}).get(name)) for name in classes)))
    return lines


def _bands_tables(results: dict, done: list[dict]) -> list[str]:
    """mIoU per distance band of the finished arms and, with contrasts, their differences (none without bands)."""
    bands = list(dict.fromkeys(name for e in done for name in e.get("bands", {})))
    if not bands:
        return []
    lines = ["", "## mIoU by distance from the sensor (%)", "", "| arm | backbone | " + " | ".join(bands) + " |"]
    lines.append("|---|---|" + "---|" * len(bands))
    for e in done:
        cells = [_pct(e["bands"][b]) if b in e.get("bands", {}) else "n/a" for b in bands]
        lines.append(f"| {e['arm']} | {e['backbone']} | " + " | ".join(cells) + " |")
    if results.get("contrasts"):
        lines += ["", "Paired by seed (points; * where the 95 % confidence interval excludes 0):", ""]
        lines += ["| arm | reference | backbone | " + " | ".join(bands) + " |", "|---|---|---|" + "---|" * len(bands)]
        for row in results["contrasts"]:
            lines.append(_contrast_row(row, " | ".join(starred(row.get("bands", {}).get(b)) for b in bands)))
    return lines


def _classes_table(done: list[dict]) -> list[str]:
    """Per-class IoU of the finished arms, in the class order of the first (none when no arm finished)."""
    if not done:
        return []
    classes = list(done[0]["iou"])
    lines = ["", "## Per-class IoU (%)", "", "| arm | backbone | " + " | ".join(classes) + " |"]
    lines.append("|---|---|" + "---|" * len(classes))
    for e in done:
        cells = [_pct(e["iou"][c]) if c in e["iou"] else "n/a" for c in classes]
        lines.append(f"| {e['arm']} | {e['backbone']} | " + " | ".join(cells) + " |")
    return lines


# ------------------------------------------------------------------------------------------------------- CLI


def add_experiment_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `u4d experiment CONFIG [key=value ...] [--out DIR]`."""
    parser.add_argument("config", type=Path, help="experiment yaml, e.g. configs/experiment/downstream_10pct.yaml")
    parser.add_argument("overrides", nargs="*", help="key=value overrides, e.g. 'seeds=[0]' 'backbones=[minkunet]'")
    parser.add_argument("--out", type=Path, default=None, help="output folder (overrides out_dir)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument(
        "--report-only", action="store_true", help="train nothing: results.json / results.md of the finished runs"
    )
    parser.add_argument(
        "--arms",
        nargs="+",
        default=None,
        metavar="NAME",
        help="train only these arms of the config (the report still covers every arm's finished runs)",
    )


def run_experiment(args: argparse.Namespace) -> int:
    """`u4d experiment`: every arm x backbone x seed at one budget, then results.json / results.md / PNGs."""
    cfg = load_config(ExperimentConfig, args.config, args.overrides)
    if args.out is not None:
        cfg.out_dir = args.out
    results = run_experiment_config(
        cfg, progress=not args.no_progress, report_only=args.report_only, train_arms=args.arms
    )
    print((Path(cfg.out_dir) / "results.md").read_text())
    return 0 if results["arms"] else 1
