"""scripts/downstream_queue.sh run end to end, both cores at once, with the stand-in `u4d` and interpreter
(tests/scripts/stand_in.py) in a scratch checkout: every call is one the real commands accept, the runs the comparison
asks for are all there (seeds per arm and setting, banks from the right nets, the selection ablation, the 1 % nets,
the transfer seeds, the generation table), each queue's waits are met by the other, and a re-run trains nothing."""

from __future__ import annotations

import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

from tests.scripts.stand_in import check_call, recorded_calls, stand_in_env
from tests.tiny_nets import REPO

SCRIPT = REPO / "scripts" / "downstream_queue.sh"
MAIN = {"sup-only", "mt", "mt+r2dm", "mt+u4d"}


def checkout(tmp_path: Path) -> Path:
    """configs/, weights/, scripts/ of the repository; benchmarks/ empty, so nothing is written into the repository."""
    root = tmp_path / "co"
    root.mkdir()
    for name in ("configs", "weights", "scripts"):
        (root / name).symlink_to(REPO / name)
    (root / "benchmarks" / "results").mkdir(parents=True)
    return root


def run_both(root: Path, env: dict) -> None:
    """CORE=A and CORE=B side by side, as on a 2-core machine (each waits for what the other writes)."""
    procs = [
        subprocess.Popen(
            ["bash", "scripts/downstream_queue.sh"],
            cwd=root,
            env={**env, "CORE": core},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for core in ("A", "B")
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=180)
        assert proc.returncode == 0, err[-3000:]


def option(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def help_flags(script: str) -> set[str]:
    """The --flags a benchmark script's own parser accepts (its --help)."""
    out = subprocess.run([sys.executable, str(REPO / script), "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return set(re.findall(r"--[a-z][a-z0-9-]*", out.stdout))


def test_the_queues_run_every_run_the_comparison_needs_and_resume_to_nothing(tmp_path):
    root = checkout(tmp_path)
    env = stand_in_env(tmp_path, WAIT="0.1")
    run_both(root, env)
    made = recorded_calls(tmp_path)

    arms: dict[tuple[str, str, int], set[str]] = defaultdict(set)  # (setting, backbone, seed) -> arms trained
    generated: dict[str, dict] = {}
    stages: dict[str, object] = {}
    seg_runs: dict[str, object] = {}
    for argv in made:
        if argv[0] == "py":
            script = argv[1]
            assert (REPO / script).is_file(), script
            assert {a.split("=")[0] for a in argv[2:] if a.startswith("--")} <= help_flags(script), argv
            continue
        args, cfg = check_call(argv, root)
        if argv[0] == "experiment":
            setting = Path(args.config).stem.removeprefix("downstream_")
            for backbone in cfg.backbones:
                for seed in cfg.seeds:
                    arms[(setting, backbone, seed)] |= set(args.arms)
            for arm in cfg.arms:  # every bank an arm reads was written, complete, before the arm ran
                if arm.name in args.arms and arm.bank is not None:
                    assert (root / arm.bank / "manifest.json").is_file(), arm.bank
        elif argv[0] == "generate":
            generated[str(args.out)] = cfg
        elif argv[0] == "train-diffusion":
            stages[str(args.out)] = cfg
        elif argv[0] == "seg-train":
            seg_runs[str(args.out)] = cfg

    # the comparison's seeds: 10 % >= 4 for every arm (>= 2 for the ablation), 1 % >= 3, SPVCNN at 10 % >= 2
    for seed in range(4):
        assert arms[("10pct", "minkunet", seed)] >= MAIN, seed
    assert sum("mt+u4d-random" in arms[("10pct", "minkunet", s)] for s in range(4)) >= 2
    for seed in range(3):
        assert arms[("1pct", "minkunet", seed)] >= MAIN, seed
    for seed in range(2):
        assert arms[("10pct", "spvcnn", seed)] >= MAIN, seed

    banks = {Path(out).name: cfg for out, cfg in generated.items()}
    assert banks["r2dm_hdl64_ms"].mode == "baseline" and banks["u4d_hdl64_ms"].mode == "u4d"
    assert banks["u4d_random_hdl64_ms"].stage1.endswith("gen64_random/stage1")
    assert banks["u4d_1pct_hdl64_ms"].stage2.endswith("gen64_1pct/stage2")
    assert all(cfg.mean_start_below == -10 for cfg in banks.values())  # every bank with the mean start
    assert len({cfg.num for cfg in banks.values()}) == 1  # every bank the same size
    for out, cfg in stages.items():  # the shipped nets' recipe for every new pair of nets
        assert cfg.steps == 8000 and cfg.width == 1024 and cfg.height == 64, out
        if "gen64_random" in out:
            assert cfg.uncertainty.strategy == "random"
        else:
            assert cfg.uncertainty.strategy == "entropy" and cfg.probs_root.endswith("sim_seg_probs_1pct"), out
    unc = seg_runs.pop(next(k for k in seg_runs if k.endswith("unc_seg_1pct")))
    assert unc.data.label_fraction == 0.01 and unc.mode == "supervised"
    worlds = sorted((Path(out).name, cfg.seed, str(cfg.data.root)) for out, cfg in seg_runs.items())
    assert worlds == [
        (f"{w}_s{s}", s, f"data/{'sim_varied' if w == 'varied' else 'sim_seg'}")
        for w in ("seg_rich", "varied")
        for s in range(3)
    ]
    scripts = [argv[1] for argv in made if argv[0] == "py"]
    assert scripts.count("benchmarks/bench_generation.py") == 2  # banks first, FRD / FPD once the extractor exists
    assert "benchmarks/transfer_table.py" in scripts

    (tmp_path / "calls.jsonl").unlink()
    run_both(root, env)
    again = {argv[0] if argv[0] != "py" else argv[1] for argv in recorded_calls(tmp_path)}
    assert again <= {"experiment", "benchmarks/transfer_table.py"}  # experiments skip their finished runs themselves
