"""What `u4d demo` runs and the report it ends with (DESIGN.md §3 order; `u4d_aug.cli.run_demo` executes the steps).

The demo simulates a small world, trains every net for seconds (to show the training loops run), generates its two
banks at 64x1024 with the shipped nets of `weights/` (trained for hours; the seconds-long nets would give noise),
scores them (BEV JSD/MMD, FRD/FPD with the shipped extractors), generates one 5-frame 4D sequence along a given ego
motion with the shipped MoST nets (frame 0 propagated) and scores its TTCE-global / CTC, runs the five downstream
arms at toy size and writes OUT/report.md: the tables, the figures and each step's wall time, every number marked
toy-scale.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from u4d_aug.trajectory import straight_motion

# The presets the demo runs with, named as `u4d` takes them from any folder (tests/u4d_aug/test_presets.py).
DEMO_PRESETS = {
    "seg": "seg/tiny",
    "diffusion": "u4d/demo",
    "generate": "u4d/generate_hdl64",
    "generate_toy": "u4d/generate_cpu",
    "generate_4d": "u4d/generate_hdl64_most",
    "experiment_base": "seg/tiny_semi",
}
SEQUENCES, FRAMES = 5, 6  # the demo world: sequences 00-01 train, 02 is held out, 03-04 feed the ceiling arm
CEILING_PLACES = "03-04"  # places no split and no net uses: the real bank of the mt+real arm
ARM_STEPS = 12  # training steps of each downstream arm (the mean teacher from step ARM_STEPS // 2)
BANK_SCANS = 8  # scans per bank: ~1 min of generation per method at 64x1024 on 2 cores
TOY_BANK_SCANS = 4  # without shipped nets: the seconds-trained nets' 32x256 scans
METHODS = ("u4d", "baseline")
# the 4D step (with the shipped MoST nets): one sequence of L frames along a fixed drive
SEQUENCE_FRAMES, SEQUENCE_STEP_M, SEQUENCE_YAW_DEG = 5, 1.2, 3.0  # 1.2 m per frame, turning left 3 degrees per frame
SEQUENCE_REAL = "02"  # the demo world's held-out sequence: the real side of TTCE / CTC
# where the full-size results live, relative to the repository root
FULL_RESULTS = {
    "generation": "benchmarks/results/generation/generation_64x1024.md",
    "generation diagnostics": "benchmarks/results/generation/generation_64x1024_diagnostics.md",
    "downstream": "benchmarks/results/downstream/",
}


REPOSITORY = Path(__file__).resolve().parents[1]


def full_results(root: Path = REPOSITORY) -> str:
    """The full-size results as text: each path, marked when it is not measured yet (or not in this install)."""
    return ", ".join(
        f"{name} `{path}`" + ("" if (root / path).exists() else " (not measured yet)")
        for name, path in FULL_RESULTS.items()
    )


@dataclass(frozen=True)
class Step:
    """One demo step: a short key (report rows), its title and the `u4d` command line that runs it."""

    key: str
    title: str
    command: list[str]


def demo_steps(out: Path, seed: int, real: Path, weights: dict[str, Path] | None) -> list[Step]:
    """Every demo step in data-flow order; `weights`: `shipped_weights()` (None: banks from the demo's own nets)."""
    world = out / "world"
    banks = {method: out / f"bank_{method}" for method in METHODS}
    steps = _world_steps(out, world, seed, real)
    steps += _segmentation_steps(out, world, seed)
    steps += _diffusion_steps(out, world, seed, weights)
    steps += _generation_steps(out, world, seed, weights, banks)
    steps += _evaluation_steps(out, world, weights, banks)
    if weights and "u4d_most_stage1" in weights and "u4d_most_stage2" in weights:
        steps += sequence_steps(out, seed, weights)
    steps.append(
        Step("downstream", "downstream, toy size: sup-only vs MT+LaserMix vs + baseline bank vs + U4D bank vs + real "
             "bank (mIoU, ECE on sequence 02)", ["experiment", str(out / "downstream.yaml"), "--no-progress"])
    )  # fmt: skip
    return steps


def _world_steps(out: Path, world: Path, seed: int, real: Path) -> list[Step]:
    """Simulate the demo world, summarise it, picture a frame and, when real scans are there, compare with them."""
    frame0 = world / "sequences" / "00" / "velodyne" / "000000.bin"
    steps = [
        Step("simulate", f"simulate a small world ({SEQUENCES} sequences x {FRAMES} frames, HDL-64E)",
             ["simulate", "--out", str(world), "--sequences", str(SEQUENCES), "--frames", str(FRAMES),
              "--seed", str(seed)]),
        Step("info", "summarise it", ["info", str(world)]),
        Step("show", "picture of frame 0: range image + BEV", ["show", str(frame0), "--png", str(out / "frame0.png")]),
    ]  # fmt: skip
    if (real / "sequences").is_dir():
        steps.append(
            Step("sim-report", "realism report against the real scans",
                 ["sim-report", str(world), "--real", str(real), "--png", str(out / "sim_vs_real.png"),
                  "--max-frames", str(FRAMES)])
        )  # fmt: skip
    return steps


def _segmentation_steps(out: Path, world: Path, seed: int) -> list[Step]:
    """Train the segmentor for seconds, evaluate it and write the probabilities U4D's uncertainty reads."""
    seg_dir = out / "seg"
    return [
        Step("seg-train", "train a small MinkUNet-like segmentor for seconds (sequences 00-01, held-out 02)",
             ["seg-train", DEMO_PRESETS["seg"], f"data.root={world}", 'data.train_sequences=["00", "01"]',
              'data.val_sequences=["02"]', "optim.steps=40", "eval_every=20", "checkpoint_every=20", f"seed={seed}",
              "--out", str(seg_dir)]),
        Step("seg-eval", "evaluate it: mIoU, ECE, reliability diagram",
             ["seg-eval", str(seg_dir / "model.pt"), str(world), "--sequences", "02", "--png",
              str(out / "reliability.png")]),
        Step("seg-predict", "per-point probabilities for U4D's uncertainty",
             ["seg-predict", str(seg_dir / "model.pt"), str(world), "--out", str(out / "probs")]),
    ]  # fmt: skip


def _diffusion_steps(out: Path, world: Path, seed: int, weights: dict[str, Path] | None) -> list[Step]:
    """Train U4D (one net for both stages) and the baseline for seconds (the training loops run; shipped nets make
    the banks)."""
    diffusion = [DEMO_PRESETS["diffusion"], f"data_root={world}", 'sequences=["00", "01"]', f"seed={seed}"]
    probs = f"probs_root={out / 'probs'}"
    check = "training loop check, seconds; the banks below use the shipped nets" if weights else "seconds"
    return [
        Step("train-u4d", f"U4D, one net for both stages (task embedding): stage 1 the uncertain region P_u + mask "
             f"head, stage 2 the completion conditioned on (x0_u, m_u) ({check})",
             ["train-diffusion", *diffusion, "stage=u4d", probs, "--out", str(out / "u4d")]),
        Step("train-baseline", f"R2DM-style baseline: one unconditional stage ({check})",
             ["train-diffusion", *diffusion, "stage=baseline", "--out", str(out / "baseline")]),
    ]  # fmt: skip


def _generation_steps(
    out: Path, world: Path, seed: int, weights: dict[str, Path] | None, banks: dict[str, Path]
) -> list[Step]:
    """Generate both banks (with the shipped nets when there are some), picture them, and bank real scans of the
    unused places for the ceiling arm."""
    if weights:
        generate = [DEMO_PRESETS["generate"], f"num={BANK_SCANS}", f"seed={seed}"]
        nets = {"u4d": [f"net={weights['u4d']}", "stage1=", "stage2="],
                "baseline": [f"baseline={weights['baseline']}"]}  # fmt: skip
        size = f"{BANK_SCANS} scans at 64x1024 with the shipped nets"
    else:
        generate = [DEMO_PRESETS["generate_toy"], "steps=16", "stage1_steps=8", f"num={TOY_BANK_SCANS}", f"seed={seed}"]
        nets = {"u4d": [f"net={out / 'u4d'}", "stage1=", "stage2="],
                "baseline": [f"baseline={out / 'baseline'}"]}  # fmt: skip
        size = f"{TOY_BANK_SCANS} scans with the seconds-trained nets (no shipped nets found)"
    return [
        Step("generate-u4d", f"generate {size}: U4D, hard regions first",
             ["generate", *generate, "mode=u4d", *nets["u4d"], "--out", str(banks["u4d"])]),
        Step("generate-baseline", f"generate {size}: the R2DM-style baseline",
             ["generate", *generate, "mode=baseline", *nets["baseline"], "--out", str(banks["baseline"])]),
        Step("gen-report", "real vs U4D vs baseline: uncertainty, stage 1, stage 2, BEV",
             ["gen-report", str(world), "--sequences", "02", "--probs", str(out / "probs"),
              "--bank", f"u4d={banks['u4d']}", "--bank", f"baseline={banks['baseline']}",
              "--png", str(out / "generated.png")]),
        Step("bank-real", f"the ceiling's bank: as many real scans of the unused places {CEILING_PLACES}, projected "
             "as the generated ones", ["bank-real", str(world), "--sequences", CEILING_PLACES, "--max-scans",
             str(BANK_SCANS if weights else TOY_BANK_SCANS), *ceiling_geometry(out, weights), "--out",
             str(out / "bank_real")]),
    ]  # fmt: skip


def _evaluation_steps(out: Path, world: Path, weights: dict[str, Path] | None, banks: dict[str, Path]) -> list[Step]:
    """Score each bank against the demo world (BEV JSD/MMD, FRD/FPD with the shipped extractors, points)."""
    # the shipped nets never saw this world: every scan of it is a held-out reference; the demo's own nets saw 00-01
    reference = [] if weights else ["--real-sequences", "02"]
    extractors = []
    for kind in ("frd", "fpd"):
        if weights and f"extractor_{kind}" in weights:
            extractors += [f"--extractor-{kind}", str(weights[f"extractor_{kind}"])]
    return [
        Step(f"evaluate-{method}", f"generation metrics of the {method} bank (BEV JSD/MMD, FRD/FPD, points)",
             ["evaluate", "--bank", str(bank), "--real", str(world), *reference,
              "--metrics", "jsd,mmd,frd,fpd,points", *extractors, "--json", "--md", "--out",
              str(out / f"eval_{method}")])
        for method, bank in banks.items()
    ]  # fmt: skip


def ceiling_geometry(out: Path, weights: dict[str, Path] | None) -> list[str]:
    """`u4d bank-real` flags giving the real bank the generated banks' range image: the shipped nets' 64 x 1024
    (its defaults), else that of the demo's own nets, which must not have trained on the bank's places."""
    if weights:
        return []
    return [
        "--like",
        str(out / "baseline"),
        "--generator",
        str(out / "u4d"),
        "--generator",
        str(out / "baseline"),
    ]


def sequence_steps(out: Path, seed: int, weights: dict[str, Path]) -> list[Step]:
    """4D: one U4D+MoST sequence along `motion_4d.npy` (written by `run_demo`), its figure, its TTCE-global / CTC."""
    bank = out / "bank_4d"
    drive = f"{SEQUENCE_FRAMES} frames, {SEQUENCE_STEP_M} m per frame turning left {SEQUENCE_YAW_DEG:g} deg"
    return [
        Step("generate-4d", f"4D: one U4D+MoST sequence of {drive}, frame 0 propagated along the motion",
             ["generate", DEMO_PRESETS["generate_4d"], "num=1", f"frames={SEQUENCE_FRAMES}", f"seed={seed}",
              f"motion_file={out / 'motion_4d.npy'}", f"stage1={weights['u4d_most_stage1']}",
              f"stage2={weights['u4d_most_stage2']}", "--out", str(bank)]),
        Step("show-4d", "picture of the sequence: its frames and a BEV of them moved by their poses",
             ["show", str(bank / "sequences" / "00"), "--png", str(out / "sequence_4d.png")]),
        Step("evaluate-4d", f"temporal metrics of the sequence (TTCE-global, CTC; real: sequence {SEQUENCE_REAL})",
             ["evaluate", "--bank", str(bank), "--real", str(out / "world"), "--real-sequences", SEQUENCE_REAL,
              "--metrics", "ttce_global,ctc", "--json", "--md", "--out", str(out / "eval_4d")]),
    ]  # fmt: skip


def sequence_motion() -> np.ndarray:
    """(L, 4) x, y, z, yaw of the demo's 4D drive (`u4d_aug.trajectory.straight_motion`)."""
    return straight_motion(SEQUENCE_FRAMES, SEQUENCE_STEP_M, np.deg2rad(SEQUENCE_YAW_DEG))


def demo_experiment(out: Path, seed: int) -> dict:
    """The demo's `u4d experiment` config: the five arms of the comparison on the demo world, its two generated
    banks and the ceiling's bank of real scans."""
    world = out / "world"
    overrides = [f"data.root={world}", 'data.train_sequences=["00", "01"]', 'data.val_sequences=["02"]']
    overrides += [f"optim.steps={ARM_STEPS}", f"semi.burn_in_steps={ARM_STEPS // 2}", f"eval_every={ARM_STEPS}"]
    overrides += [f"checkpoint_every={ARM_STEPS // 2}", "log_every=2"]
    return {
        "base": DEMO_PRESETS["experiment_base"],
        "overrides": overrides,
        "arms": [
            {"name": "sup-only", "mode": "supervised"},
            {"name": "mt", "mode": "semi"},
            {"name": "mt+baseline", "mode": "semi", "bank": str(out / "bank_baseline"), "bank_ratio": 0.5},
            {"name": "mt+u4d", "mode": "semi", "bank": str(out / "bank_u4d"), "bank_ratio": 0.5},
            {"name": "mt+real", "mode": "semi", "bank": str(out / "bank_real"), "bank_ratio": 0.5},
        ],
        "contrasts": [["mt+u4d", "mt"], ["mt+u4d", "mt+baseline"], ["mt+real", "mt"]],
        "backbones": ["minkunet"],
        "seeds": [seed],
        "final_eval": True,
        "out_dir": str(out / "downstream"),
    }


def _read_json(path: Path) -> dict | None:
    """A step's json output, or None when the step did not write it."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _cell(entry: dict | None, digits: int = 3) -> str:
    """A metric entry of `u4d evaluate` as a table cell: its value, or why it is absent."""
    if not entry:
        return "not run"
    if entry.get("value") is None:
        return f"absent: {entry.get('missing', 'no value')}"
    value = entry["value"]
    return f"{value:.{digits}f}" if abs(value) < 1000 else f"{value:.0f}"


def generation_table(out: Path, weights: dict[str, Path] | None) -> list[str]:
    """Markdown lines: BEV JSD/MMD, FRD, FPD and points per scan of both banks against the demo world."""
    lines = [
        "| bank | scans | real scans | JSD | MMD (x1e-4) | FRD | FPD | points per scan |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for method in METHODS:
        result = _read_json(out / f"eval_{method}" / "evaluation.json")
        if result is None:
            lines.append(f"| {method} | not run | | | | | | |")
            continue
        table = result.get("table1", {})
        points = table.get("points", {})
        point_cell = f"{points['value']:.0f} (real {points['real']:.0f})" if points.get("value") is not None else "-"
        cells = [_cell(table.get(name), 3 if name == "jsd" else 1) for name in ("jsd", "mmd", "frd", "fpd")]
        for i, kind in ((2, "frd"), (3, "fpd")):
            if table.get(kind, {}).get("value") is None and f"extractor_{kind}" not in (weights or {}):
                cells[i] = f"absent: no shipped {kind.upper()} extractor (weights/extractor_{kind}.pt)"
        counts = f"{result['counts']['bank']} | {result['counts']['real']}"
        lines.append(f"| {method} | {counts} | {' | '.join(cells)} | {point_cell} |")
    if weights:
        note = (
            "Banks from the shipped 64x1024 nets (`weights/`), scored against every scan of the demo world (those nets "
            "never saw it). FRD/FPD from this few scans are far noisier than the 64-scan tables."
        )
    else:
        note = (
            "No shipped nets were found (a wheel install without `weights/`): the banks come from the seconds-trained "
            "demo nets and are close to noise."
        )
    lines += ["", note]
    return lines


def downstream_table(out: Path) -> list[str]:
    """Markdown lines: mIoU and ECE of the arms and the contrasts, from the experiment's results.json."""
    results = _read_json(out / "downstream" / "results.json")
    if results is None:
        return ["The downstream step did not finish: no `downstream/results.json`."]
    lines = ["| arm | status | mIoU % | ECE per scan % | ECE pooled % |", "|---|---|---|---|---|"]
    for arm in results.get("arms", []):
        values = [arm.get(key, {}).get("mean") for key in ("miou", "ece_per_scan", "ece_pooled")]
        cells = " | ".join("-" if v is None else f"{100 * v:.2f}" for v in values)
        lines.append(f"| {arm['arm']} | {arm['status']} | {cells} |")
    contrasts = results.get("contrasts", [])
    if contrasts:
        lines += ["", "| arm - reference | mIoU points | ECE per scan points |", "|---|---|---|"]
        for contrast in contrasts:
            miou, ece = contrast.get("miou", {}), contrast.get("ece_per_scan", {})
            signed = [f"{100 * s['mean']:+.2f}" if s.get("mean") is not None else "-" for s in (miou, ece)]
            lines.append(f"| {contrast['arm']} - {contrast['reference']} | {signed[0]} | {signed[1]} |")
    return lines


def sequence_table(out: Path) -> list[str]:
    """Markdown lines: TTCE-global and CTC of the generated sequence against the demo world's real sequence."""
    result = _read_json(out / "eval_4d" / "evaluation.json")
    if result is None:
        return ["The 4D step did not run (it needs the shipped 4D nets `weights/u4d_most_stage*.pt`)."]
    table = result.get("table2", {})
    keys = [("ttce_global", "3"), ("ttce_global", "4"), *[("ctc", k) for k in "1234"]]
    lines = [
        "| sequence | TTCE-global k=3 (m) | k=4 (m) | CTC k=1 (m²) | k=2 | k=3 | k=4 |",
        "|---|---|---|---|---|---|---|",
    ]
    for side, name in (("bank", "generated (U4D+MoST, propagated)"), ("real", f"real (sequence {SEQUENCE_REAL})")):
        values = [table.get(side, {}).get(metric, {}).get(k) for metric, k in keys]
        lines.append(f"| {name} | " + " | ".join("-" if v is None else f"{v:.3f}" for v in values) + " |")
    lines += [
        "",
        "TTCE-global: ICP (started from a global registration) between frames k apart against the poses the "
        "sequence was generated for; CTC: chamfer distance of frames aligned by those poses. One sequence: read "
        "it as a check that the frames follow their motion, not as a score.",
    ]
    return lines


def demo_report(out: Path, timings: list[tuple[Step, float]], weights: dict[str, Path] | None) -> str:
    """OUT/report.md: wall time per step, the generation table, the downstream table, the figures, the full results."""
    total = sum(seconds for _, seconds in timings)
    lines = [
        "# u4d demo report",
        "",
        f"**Toy scale.** Every number below comes from a world of {SEQUENCES * FRAMES} scans, nets trained for seconds "
        f"and one seed of {ARM_STEPS} training steps per arm: it shows that every stage runs and feeds the next, not "
        "whether U4D helps. The full-size results: " + full_results() + ".",
        "",
        "## Generation",
        "",
        *generation_table(out, weights),
        "",
        "## Downstream: the five arms, the last a ceiling of real scans (toy size, one seed)",
        "",
        *downstream_table(out),
        "",
        "## 4D: a sequence that follows its ego motion (one sequence)",
        "",
        *sequence_table(out),
        "",
        "## Figures",
        "",
    ]
    figures = {
        "frame0.png": "a simulated scan: range image and BEV",
        "generated.png": "uncertainty map of a real scan, then real vs U4D (stage 1, stage 2) vs baseline",
        "sequence_4d.png": "the generated 4D sequence: its frames, and a BEV of them moved by their poses",
        "reliability.png": "reliability diagram of the seconds-trained segmentor",
        "sim_vs_real.png": "the simulated world against the real scans",
    }
    results = _read_json(out / "downstream" / "results.json") or {}
    for arm in results.get("arms", []):
        if arm.get("reliability_png"):
            figures[f"downstream/{arm['reliability_png']}"] = f"reliability diagram of the {arm['arm']} arm"
    for name, caption in figures.items():
        if (out / name).is_file():
            lines.append(f"- {caption}: ![{caption}]({name})")
    lines += ["", f"## Wall time of this run ({total:.0f} s)", "", "| # | step | s |", "|---|---|---|"]
    lines += [f"| {i} | {step.title} | {seconds:.1f} |" for i, (step, seconds) in enumerate(timings, start=1)]
    return "\n".join(lines) + "\n"
