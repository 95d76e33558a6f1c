"""scripts/downstream_queue.sh run end to end, both cores at once, with the stand-in `u4d` (tests/scripts/stand_in.py)
in a scratch checkout: every call is one the real commands accept, the runs the comparison asks for are all there
(seeds per arm and setting, banks from the right nets, the selection ablation, the 1 % nets exported to weights/),
each queue's waits are met by the other, a re-run trains nothing, and on a new machine (no run folders, world or
banks) the committed records and weights leave nothing to train."""

from __future__ import annotations

import shutil
from collections import defaultdict
from pathlib import Path

from tests.scripts.stand_in import check_call, recorded_calls, run_both, stand_in_env
from tests.tiny_nets import REPO

SCRIPT = REPO / "scripts" / "downstream_queue.sh"
MAIN = {"sup-only", "mt", "mt+r2dm", "mt+u4d"}


EXPORTED = (
    "u4d_1pct_stage1",
    "u4d_1pct_stage2",
    "u4d_random_stage1",
    "u4d_random_stage2",
    "uncertainty_segmentor_1pct",
)


def checkout(tmp_path: Path) -> Path:
    """configs/ and scripts/ of the repository, weights/ a folder of links to its files but the ones the queues export
    (the queues start from the beginning, whichever of them are committed), benchmarks/ empty: what the queues write
    (records, exported nets) stays in the scratch checkout."""
    root = tmp_path / "co"
    root.mkdir()
    for name in ("configs", "scripts"):
        (root / name).symlink_to(REPO / name)
    (root / "weights").mkdir()
    for path in (REPO / "weights").iterdir():
        if path.stem not in EXPORTED:
            (root / "weights" / path.name).symlink_to(path)
    (root / "benchmarks" / "results").mkdir(parents=True)
    return root


def option(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def test_the_queues_run_every_run_the_comparison_needs_and_resume_to_nothing(tmp_path):
    root = checkout(tmp_path)
    env = stand_in_env(tmp_path, WAIT="0.1")
    run_both(SCRIPT, root, env)
    made = recorded_calls(tmp_path)

    arms: dict[tuple[str, str, int], set[str]] = defaultdict(set)  # (setting, backbone, seed) -> arms trained
    generated: dict[str, dict] = {}
    stages: dict[str, object] = {}
    seg_runs: dict[str, object] = {}
    for argv in made:
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
    assert banks["u4d_random_hdl64_ms"].stage1 == "weights/u4d_random_stage1.pt"  # from the exported nets
    assert banks["u4d_1pct_hdl64_ms"].stage2 == "weights/u4d_1pct_stage2.pt"
    assert all(cfg.mean_start_below == -10 for cfg in banks.values())  # every bank with the mean start
    assert len({cfg.num for cfg in banks.values()}) == 1  # every bank the same size
    for out, cfg in stages.items():  # the shipped nets' recipe for every new pair of nets
        assert cfg.steps == 8000 and cfg.width == 1024 and cfg.height == 64, out
        if "gen64_random" in out:
            assert cfg.uncertainty.strategy == "random" and cfg.probs_root.endswith("sim_seg_probs"), out
        else:
            assert cfg.uncertainty.strategy == "entropy" and cfg.probs_root.endswith("sim_seg_probs_1pct"), out
    assert sorted(Path(out).name for out in stages) == ["stage1", "stage1", "stage2", "stage2"]
    (unc,) = seg_runs.values()
    assert unc.data.label_fraction == 0.01 and unc.mode == "supervised"
    exported = sorted(option(argv, "--out") for argv in made if argv[0] == "export-weights")
    assert exported == [f"weights/{name}.pt" for name in EXPORTED]
    records = sorted((root / "benchmarks" / "results" / "downstream" / "records").rglob("*.json"))
    assert len(records) == 4 * 4 + 2 + 3 * 4 + 2 * 4  # 10 %, the ablation's 2 seeds, 1 %, SPVCNN

    (tmp_path / "calls.jsonl").unlink()
    run_both(SCRIPT, root, env)
    assert recorded_calls(tmp_path) == []  # every run has its record: nothing runs again

    # the world and banks live beside the run folders, linked into the checkout: a fresh checkout finds them again
    for name in ("data", "banks"):
        assert (root / name).resolve() == (tmp_path / "runs" / name).resolve()
        (root / name).unlink()
    run_both(SCRIPT, root, env)
    assert recorded_calls(tmp_path) == []

    # a new machine: the checkout (records, exported nets) without run folders, world or banks
    for name in ("data", "banks"):
        (root / name).unlink()
    shutil.rmtree(tmp_path / "runs")
    run_both(SCRIPT, root, env)
    assert [argv[0] for argv in recorded_calls(tmp_path)] == ["simulate"]
