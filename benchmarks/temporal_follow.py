"""Do generated sequences follow their conditioning ego motion? ICP translations against the poses, per bank.

    python benchmarks/temporal_follow.py --bank u4d_most=runs/temporal/banks/u4d_most_s1 \
        --bank floor=runs/temporal/floor --out benchmarks/results/temporal/temporal_follow

TTCE alone cannot tell a sequence that moves a little wrong from one that does not move at all: with the car
driving ~0.9 m per frame, a static scene (ICP finds no motion) scores TTCE k = 3 of about |t|/3 ~ 0.9 m. For every
pair (i, i + k), k = 1..4, this takes the ICP translation of TTCE (u4d_aug.metrics.temporal.icp_translations, the same
settings) and the conditioning translation from poses.txt, and reports per k: the mean length of each, the gain
sum(t_icp . t_pose) / sum(|t_pose|^2) (1: the frames move as the poses say; 0: they do not move), TTCE against the
poses, and TTCE against standing still (t_pose = 0). Writes OUT.json, OUT.md and OUT.png (ICP against pose
translation length per pair, one panel per bank, k = 1 and 3).

OUT.json: intervals; registration;
    banks.NAME: {path, sequences, k: {pairs, pose_m, icp_m, gain, ttce_poses, ttce_still}}
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from u4d_aug.bank import named_banks, sequence_ids
from u4d_aug.errors import InputError, exit_code_of
from u4d_aug.io import atomic_write_json, atomic_write_text, make_folder
from u4d_aug.metrics import temporal
from u4d_aug.progress import progress_bar
from u4d_aug.viz import plt, save_figure

INTERVALS = (1, 2, 3, 4)
PLOTTED = (1, 3)


def follow_scores(estimates: np.ndarray, truths: np.ndarray) -> dict[str, float | int]:
    """Pairs (P, 3) of ICP and pose translations -> lengths, gain of ICP on the poses, TTCE against poses / still."""
    estimates = np.asarray(estimates, dtype=np.float64).reshape(-1, 3)
    truths = np.asarray(truths, dtype=np.float64).reshape(-1, 3)
    if len(estimates) == 0:
        nan = float("nan")
        return {"pairs": 0, "pose_m": nan, "icp_m": nan, "gain": nan, "ttce_poses": nan, "ttce_still": nan}
    power = float(np.sum(truths * truths))
    return {
        "pairs": len(estimates),
        "pose_m": float(np.linalg.norm(truths, axis=1).mean()),
        "icp_m": float(np.linalg.norm(estimates, axis=1).mean()),
        "gain": float(np.sum(estimates * truths) / power) if power > 0 else float("nan"),
        "ttce_poses": float(np.abs(estimates - truths).mean()),  # mean over pairs and x, y, z, as TTCE
        "ttce_still": float(np.abs(estimates).mean()),
    }


def bank_translations(
    root: Path, progress: bool = True, registration: temporal.Registration = "icp"
) -> tuple[list[str], dict[int, tuple[np.ndarray, np.ndarray]]]:
    """Sequence ids and, per k, (ICP (P, 3), pose (P, 3)) translations pooled over the bank's sequences
    (`registration` "global": ICP from a FPFH + RANSAC registration, TTCE-global's)."""
    ids = sequence_ids(root)
    pooled: dict[int, tuple[list, list]] = {k: ([], []) for k in INTERVALS}
    for seq in progress_bar(ids, desc=root.name, unit="sequence", enabled=progress, leave=False):
        scans, poses = temporal.load_kitti_sequence(root / "sequences" / seq)
        for k, (est, truth) in temporal.icp_translations(scans, poses, INTERVALS, registration=registration).items():
            pooled[k][0].append(est)
            pooled[k][1].append(truth)
    return ids, {k: (np.concatenate(e), np.concatenate(t)) for k, (e, t) in pooled.items()}


def plot(pairs: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]], path: Path) -> None:
    """ICP translation length against pose translation length per pair, one panel per bank."""
    fig, axes = plt.subplots(1, len(pairs), figsize=(3.2 * len(pairs), 3.2), squeeze=False, sharex=True, sharey=True)
    top = max(float(np.linalg.norm(t, axis=1).max(initial=0.0)) for p in pairs.values() for _, t in p.values())
    for ax, (name, per_k) in zip(axes[0], pairs.items()):
        for k in PLOTTED:
            est, truth = per_k[k]
            ax.scatter(np.linalg.norm(truth, axis=1), np.linalg.norm(est, axis=1), s=8, alpha=0.6, label=f"k={k}")
        ax.plot([0, top], [0, top], "k--", lw=0.8, label="follows")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("pose translation (m)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("ICP translation (m)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Do the frames move as the conditioning poses say?", fontsize=10)
    save_figure(fig, path)


def markdown(result: dict, command: str, figure: str) -> str:
    """OUT.md: one row per bank and k."""
    start = {"icp": "from the identity, TTCE's", "global": "from a FPFH + RANSAC registration, TTCE-global's"}
    lines = [
        "# Do generated sequences follow their conditioning motion?",
        "",
        f"Per pair (i, i + k): ICP translation ({start[result['registration']]}) against the pose translation. "
        "gain = sum(t_icp . t_pose) / "
        "sum(|t_pose|^2): 1 = the frames move as the poses say, 0 = they do not move. TTCE against the poses and "
        "against standing still (t_pose = 0), m.",
        "",
        "| bank | k | pairs | pose (m) | ICP (m) | gain | TTCE vs poses (m) | TTCE vs still (m) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in result["banks"].items():
        for k in INTERVALS:
            s = entry[str(k)]
            lines.append(
                f"| {name} | {k} | {s['pairs']} | {s['pose_m']:.2f} | {s['icp_m']:.2f} | {s['gain']:.2f} | "
                f"{s['ttce_poses']:.3f} | {s['ttce_still']:.3f} |"
            )
    lines += ["", f"![ICP against pose translation]({figure})", "", f"    {command}", ""]
    return "\n".join(lines)


def run(argv: list[str] | None = None) -> int:
    """Score the banks, write OUT.json, OUT.md and OUT.png, print the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bank", action="append", default=[], help="NAME=DIR (a generated bank or real sequences)")
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.json, OUT.md and OUT.png")
    parser.add_argument(
        "--registration",
        choices=temporal.REGISTRATIONS,
        default="icp",
        help="where ICP starts: icp = the identity (TTCE, LC), global = a FPFH + RANSAC registration (TTCE-global)",
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if not args.bank:
        raise InputError("--bank: give at least one NAME=DIR")
    banks = named_banks(args.bank)
    result: dict = {"intervals": list(INTERVALS), "registration": args.registration, "banks": {}}
    pairs = {}
    for name, root in banks.items():
        ids, pairs[name] = bank_translations(root, not args.no_progress, args.registration)
        result["banks"][name] = {"path": str(root), "sequences": ids}
        result["banks"][name].update({str(k): follow_scores(*pairs[name][k]) for k in INTERVALS})
    make_folder(args.out.parent)
    figure = f"{args.out.name}.png"
    plot(pairs, args.out.parent / figure)
    command = "python benchmarks/temporal_follow.py " + " ".join(sys.argv[1:] if argv is None else argv)
    text = markdown(result, command, figure)
    result["figure"] = figure
    atomic_write_json(args.out.parent / f"{args.out.name}.json", result)
    atomic_write_text(args.out.parent / f"{args.out.name}.md", text)
    print(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    """`run`, with bad input (a bank, a NAME=DIR) as a one-line error and exit code 2."""
    return exit_code_of(run, argv)


if __name__ == "__main__":
    sys.exit(main())
