"""How the teacher sees each unlabelled source: the share of points it keeps as pseudo-labels, its mean confidence and
entropy, and the class mix of its pseudo-labels, on the real unlabelled scans and on each generated bank.

The bank arms of benchmarks/results/downstream draw half of each step's unlabelled scans from a bank; LaserMix trains
the student on the teacher's labels where the teacher's softmax confidence reaches semi.pseudo_threshold
(`segmentation.mean_teacher.pseudo_labels`). A teacher that is unsure on generated scans gives the student fewer and
other labels there. Each scan is cut and augmented as the mean teacher's unlabelled stream does
(`segmentation.teacher_view.teacher_logits`, as `segmentation.semi.load_unlabeled` does: data.sector_deg,
data.max_points, the checkpoint's augment config), with a generator seeded by the scan's index; the real scans are
the unlabelled part of the checkpoint's split, where the world's labels also give the accuracy of the kept
pseudo-labels. The checkpoint is the teacher at the start of the mean-teacher phase: the supervised burn-in
(`burn_in.pt` of a sup-only run).

  python benchmarks/bank_confidence.py --checkpoint RUNS/downstream_10pct/runs/sup-only/minkunet/seed2/burn_in.pt \
    --real data/sim_seg --bank mt+r2dm=banks/r2dm_hdl64_ms --bank mt+u4d=banks/u4d_hdl64_ms --scans 64 \
    --out benchmarks/results/downstream/bank_confidence

Writes OUT/bank_confidence.json, OUT/bank_confidence.md, OUT/bank_confidence.png (pseudo-label class mix) and
OUT/bank_confidence_examples.png (one scan per source in bird's-eye view, coloured by the teacher's labels).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

from segmentation.config import SegTrainConfig, class_names
from segmentation.semi import unlabeled_stream
from segmentation.teacher_view import load_teacher, teacher_logits
from u4d_aug.data.datasets import ScanDataset
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import atomic_write_json, atomic_write_text, make_folder
from u4d_aug.progress import progress_bar


def evenly_spaced(count: int, wanted: int) -> list[int]:
    """`wanted` indices spread evenly over range(count) (all of them when there are fewer)."""
    if count <= wanted:
        return list(range(count))
    return sorted(set(np.linspace(0, count - 1, wanted).round().astype(int).tolist()))


@torch.no_grad()
def source_statistics(
    model: torch.nn.Module,
    source: ScanDataset,
    cfg: SegTrainConfig,
    scans: int,
    what: str,
    progress: bool,
    intensity: float | None = None,
) -> dict:
    """Pooled over the points of `scans` scans of `source`: kept share, mean confidence, mean entropy / log K, the
    class shares (K,) of the kept pseudo-labels, and where the scans have labels their accuracy and the true shares.
    `intensity`: every point's intensity set to this value first (geometry alone), None = the scans' own."""
    k = cfg.model.num_classes
    ignore = cfg.data.label_set.ignore_index
    points_seen = kept_total = correct = scored = 0
    confidence_sum = entropy_sum = 0.0
    kept_classes = np.zeros(k, dtype=np.int64)
    true_classes = np.zeros(k, dtype=np.int64)
    picked = evenly_spaced(len(source), scans)
    for index in progress_bar(picked, desc=what, unit="scan", enabled=progress, leave=False):
        item = source[index]
        scan = torch.from_numpy(item["points"])  # (N, 4)
        if intensity is not None:
            scan = scan.clone()
            scan[:, 3] = intensity
        logits, keep = teacher_logits(model, scan, cfg, torch.Generator().manual_seed(index))  # (N', K), (N',)
        probs = torch.softmax(logits, dim=1)  # (N', K)
        confidence, labels = probs.max(dim=1)  # (N',), (N',)
        kept = confidence >= cfg.semi.pseudo_threshold
        entropy = -(probs * probs.clamp_min(1e-12).log()).sum(dim=1) / math.log(k)  # (N',) in [0, 1]
        points_seen += int(labels.numel())
        kept_total += int(kept.sum())
        confidence_sum += float(confidence.sum())
        entropy_sum += float(entropy.sum())
        kept_classes += np.bincount(labels[kept].numpy(), minlength=k)[:k]
        if item["labels"] is not None:
            truth = torch.from_numpy(item["labels"])[keep]  # (N',) train ids
            valid = truth != ignore
            true_classes += np.bincount(truth[valid].numpy(), minlength=k)[:k]
            scored_here = kept & valid
            scored += int(scored_here.sum())
            correct += int((labels[scored_here] == truth[scored_here]).sum())
    if points_seen == 0:
        raise InputError(f"{what}: the picked scans hold no point")
    return {
        "scans": len(picked),
        "points": points_seen,
        "kept": kept_total / points_seen,
        "confidence": confidence_sum / points_seen,
        "entropy": entropy_sum / points_seen,
        "kept_class_share": (kept_classes / max(kept_total, 1)).tolist(),
        "kept_accuracy": correct / scored if scored else None,
        "true_class_share": (true_classes / true_classes.sum()).tolist() if true_classes.sum() else None,
    }


def parse_banks(texts: list[str]) -> dict[str, Path]:
    """--bank NAME=DIR, repeatable: {name: folder}."""
    banks = {}
    for text in texts:
        name, sep, folder = text.partition("=")
        if not sep or not name or not folder:
            raise InputError(f"--bank {text!r}: expected NAME=DIR, e.g. mt+u4d=banks/u4d_hdl64_ms")
        if not Path(folder).is_dir():
            raise InputError(f"--bank {text!r}: {folder} is not a folder")
        banks[name] = Path(folder)
    return banks


def teacher_and_sources(
    checkpoint: Path, real: Path, banks: dict[str, Path]
) -> tuple[SegTrainConfig, torch.nn.Module, dict[str, ScanDataset]]:
    """The checkpoint's config (data.root = `real`, no banks), its net in eval mode, and the sources: the unlabelled
    part of its split of `real` ("real unlabelled"), then each bank."""
    cfg, model = load_teacher(checkpoint)
    cfg.data.root, cfg.semi.banks = real, []
    sources = {"real unlabelled": unlabeled_stream(cfg).sources[0]}
    sources.update({name: ScanDataset(folder, None) for name, folder in banks.items()})
    return cfg, model, sources


def measure(
    checkpoints: list[Path],
    real: Path,
    banks: dict[str, Path],
    scans: int,
    progress: bool,
    intensity: float | None = None,
) -> dict:
    """{checkpoints: [...], sources: {name: {per_checkpoint: [...], mean: {...}}}, class_names, threshold}."""
    per_source: dict[str, list[dict]] = {}
    threshold = names = None
    for checkpoint in checkpoints:
        cfg, model, sources = teacher_and_sources(checkpoint, real, banks)
        threshold, names = cfg.semi.pseudo_threshold, class_names(cfg)
        for name, source in sources.items():
            what = f"{checkpoint.parent.name} {name}"
            stats = source_statistics(model, source, cfg, scans, what, progress, intensity)
            per_source.setdefault(name, []).append(stats)
    result = {"checkpoints": [str(c) for c in checkpoints], "pseudo_threshold": threshold, "scans": scans}
    result["intensity"] = intensity
    result["class_names"] = names
    result["sources"] = {}
    for name, runs in per_source.items():
        mean = {key: float(np.mean([r[key] for r in runs])) for key in ("kept", "confidence", "entropy")}
        accuracies = [r["kept_accuracy"] for r in runs if r["kept_accuracy"] is not None]
        mean["kept_accuracy"] = float(np.mean(accuracies)) if accuracies else None
        mean["kept_class_share"] = np.mean([r["kept_class_share"] for r in runs], axis=0).tolist()
        result["sources"][name] = {"per_checkpoint": runs, "mean": mean}
    return result


def markdown(result: dict, command: str) -> str:
    """The table per source and the classes whose pseudo-label share differs most from the real scans'."""
    lines = [
        "# The teacher on each unlabelled source",
        "",
        f"Generated by `{command}` (do not edit by hand).",
        f"Teacher: {', '.join(f'`{c}`' for c in result['checkpoints'])}; {result['scans']} scans per source, cut and "
        f"augmented as the unlabelled stream does; kept = softmax confidence >= {result['pseudo_threshold']}; "
        "entropy / log K. Means over the checkpoints."
        + ("" if result["intensity"] is None else f" Every point's intensity set to {result['intensity']}."),
        "",
        "| source | kept % | mean confidence | mean entropy | kept pseudo-label accuracy % |",
        "|---|---|---|---|---|",
    ]
    for name, entry in result["sources"].items():
        m = entry["mean"]
        accuracy = "-" if m["kept_accuracy"] is None else f"{100 * m['kept_accuracy']:.1f}"
        lines.append(f"| {name} | {100 * m['kept']:.1f} | {m['confidence']:.3f} | {m['entropy']:.3f} | {accuracy} |")
    real = np.asarray(result["sources"]["real unlabelled"]["mean"]["kept_class_share"])
    lines += ["", "Pseudo-label class shares, % of kept points (the classes that differ most from the real scans):", ""]
    names = result["class_names"]
    for name, entry in result["sources"].items():
        if name == "real unlabelled":
            continue
        share = np.asarray(entry["mean"]["kept_class_share"])
        order = np.argsort(-np.abs(share - real))[:6]
        cells = ", ".join(f"{names[c]} {100 * share[c]:.1f} (real {100 * real[c]:.1f})" for c in order)
        lines.append(f"- {name}: {cells}")
    return "\n".join(lines) + "\n"


@torch.no_grad()
def plot_examples(checkpoint: Path, real: Path, banks: dict[str, Path], scans: int, path: Path) -> None:
    """BEV of one whole scan per source (the middle of the picked ones), coloured by the teacher's class where it is
    confident and grey where its label would be dropped."""
    from u4d_aug.viz import draw_bev, label_colors, plt, save_figure

    cfg, model, sources = teacher_and_sources(checkpoint, real, banks)
    fig, axes = plt.subplots(1, len(sources), figsize=(5 * len(sources), 5.2), squeeze=False)
    for ax, (name, source) in zip(axes[0], sources.items()):
        picked = evenly_spaced(len(source), scans)
        item = source[picked[len(picked) // 2]]
        probs = torch.softmax(model([torch.from_numpy(item["points"])]).float(), dim=1)  # (N, K)
        confidence, labels = probs.max(dim=1)
        colors = label_colors(labels.numpy(), cfg.model.num_classes)
        colors[(confidence < cfg.semi.pseudo_threshold).numpy()] = 0.35
        title = f"{name}: seq {item['seq']} frame {item['frame']} ({len(labels):,} points)"
        draw_bev(ax, item["points"], colors, extent=40.0, title=title, point_size=0.3)
    fig.suptitle(
        f"The teacher's pseudo-labels (grey: confidence < {cfg.semi.pseudo_threshold}); {checkpoint}", fontsize=9
    )
    save_figure(fig, path)


def plot(result: dict, path: Path) -> None:
    """Bars: the kept pseudo-labels' class shares per source."""
    from u4d_aug.viz import plt, save_figure

    names = result["class_names"]
    sources = list(result["sources"])
    width = 0.8 / len(sources)
    fig, ax = plt.subplots(figsize=(12, 4))
    x = np.arange(len(names))
    for i, name in enumerate(sources):
        mean = result["sources"][name]["mean"]
        label = f"{name} (kept {100 * mean['kept']:.0f} %)"
        ax.bar(x + (i - (len(sources) - 1) / 2) * width, 100 * np.asarray(mean["kept_class_share"]), width, label=label)
    ax.set_xticks(x, names, rotation=60, ha="right")
    ax.set_ylabel("% of kept pseudo-labels")
    ax.set_title("The teacher's confident pseudo-labels on each unlabelled source")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def run(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, action="append", required=True, help="teacher (repeatable)")
    parser.add_argument("--real", type=Path, required=True, help="the world the checkpoint trained on")
    parser.add_argument("--bank", action="append", default=[], metavar="NAME=DIR", help="a bank (repeatable)")
    parser.add_argument("--scans", type=int, default=64, help="scans per source, evenly spaced")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--intensity", type=float, default=None, help="set every point's intensity to this value (geometry alone)"
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.scans < 1:
        raise InputError(f"--scans must be >= 1, got {args.scans}")
    make_folder(args.out)  # a file in the way: one line before the long computation
    torch.set_num_threads(1)
    banks = parse_banks(args.bank)
    result = measure(args.checkpoint, args.real, banks, args.scans, not args.no_progress, args.intensity)
    command = "python benchmarks/bank_confidence.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = markdown(result, command)
    print(text)
    atomic_write_json(args.out / "bank_confidence.json", result)
    atomic_write_text(args.out / "bank_confidence.md", text)
    plot(result, args.out / "bank_confidence.png")
    plot_examples(args.checkpoint[0], args.real, banks, args.scans, args.out / "bank_confidence_examples.png")
    return 0


def main(argv: list[str] | None = None) -> int:
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
