"""scripts/temporal_queue.sh run end to end with a stand-in `u4d` on PATH that records each call and writes what the
real command would leave behind: every call must be one the real commands accept (configs and overrides through the
real loaders, evaluate/gates arguments through the real parsers), the budgets must be equal, the table must come out
of benchmarks/temporal_table.py, and a second run must start nothing."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.tiny_nets import REPO
from u4d_aug.config import load_config
from u4d_aug.gates import add_gates_arguments
from u4d_aug.generate import GenerateConfig
from u4d_aug.metrics.evaluate import add_evaluate_arguments
from u4d_aug.train import DiffusionTrainConfig, split_stage_override

SCRIPT = REPO / "scripts" / "temporal_queue.sh"

FAKE_U4D = """#!{python}
import json, os, sys
from pathlib import Path
argv = sys.argv[1:]
with open(os.environ["FAKE_LOG"], "a") as log:
    log.write(json.dumps(argv) + "\\n")
out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else None
command = argv[0]
if command == "train-diffusion":
    steps = int(next(a for a in argv if a.startswith("steps=")).split("=", 1)[1])
    out.mkdir(parents=True, exist_ok=True)
    (out / "log.jsonl").write_text(json.dumps({{"step": steps}}) + "\\n")
elif command == "generate":
    out.mkdir(parents=True, exist_ok=True)
    (out / "manifest.json").write_text(json.dumps({{"complete": True}}))
elif command == "evaluate":
    out.mkdir(parents=True, exist_ok=True)
    value = float(len(str(out)) % 7 + 1)
    bank = {{"ttce": {{"3": value, "4": value + 1}}, "ctc": {{str(k): value * k for k in range(1, 5)}}}}
    result = {{"table1": {{"frd": {{"value": 100 * value}}}}, "table2": {{"bank": bank}}}}
    (out / "evaluation.json").write_text(json.dumps(result))
elif command == "gates":
    print("{{}}")
"""


def run_queue(core: str, env: dict) -> subprocess.CompletedProcess:
    result = subprocess.run(
        ["bash", str(SCRIPT)], cwd=REPO, env={**env, "CORE": core}, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def calls(log: Path) -> list[list[str]]:
    return [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []


@pytest.fixture
def queue_env(tmp_path: Path) -> tuple[dict, Path]:
    """PATH with the stand-in u4d first, RUNS / DATA / RESULTS in tmp_path, held-out places 88-99 present."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "u4d"
    fake.write_text(FAKE_U4D.format(python=sys.executable))
    fake.chmod(0o755)
    for seq in range(88, 100):
        (tmp_path / "data" / "sim_seg" / "sequences" / str(seq)).mkdir(parents=True)
    env = {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        "FAKE_LOG": str(tmp_path / "calls.jsonl"),
        "RUNS": str(tmp_path / "runs"),
        "DATA": str(tmp_path / "data"),
        "RESULTS": str(tmp_path / "results"),
        "STEPS": "20",
    }
    return env, tmp_path


def option(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def overrides_of(argv: list[str], skip: int) -> list[str]:
    """The key=value arguments after the command and its config."""
    return [a for a in argv[skip:] if "=" in a and not a.startswith("--")]


def test_every_call_is_valid_budgets_are_equal_and_the_table_is_written(queue_env):
    env, tmp = queue_env
    run_queue("B", env)  # core A waits for B's evaluations: B first, so nothing waits
    run_queue("A", env)
    made = calls(tmp / "calls.jsonl")
    steps: dict[str, int] = {}
    for argv in made:
        if argv[0] == "train-diffusion":
            assert argv[1] == "configs/u4d/cpu_hdl64_most.yaml"
            cfg = load_config(DiffusionTrainConfig, REPO / argv[1], split_stage_override(overrides_of(argv, 2)))
            assert (REPO / cfg.init_from).is_file(), cfg.init_from  # the shipped net of this stage
            assert Path(cfg.init_from).stem.endswith(cfg.diffusion.stage)
            assert cfg.data_root == f"{tmp}/data/sim_seg" and cfg.frames == 4
            steps[option(argv, "--out")] = cfg.steps
        elif argv[0] == "generate":
            cfg = load_config(GenerateConfig, REPO / argv[1], overrides_of(argv, 2))
            assert cfg.frames == 5 and cfg.num == 24  # TTCE k = 4 needs 5 frames
        elif argv[0] == "evaluate":
            parser = argparse.ArgumentParser()
            add_evaluate_arguments(parser)
            args = parser.parse_args(argv[1:])
            assert args.real_sequences == ["88-99"] and args.json
        elif argv[0] == "gates":
            parser = argparse.ArgumentParser()
            add_gates_arguments(parser)
            parser.parse_args(argv[1:])
        else:
            raise AssertionError(f"unexpected command {argv}")

    runs = tmp / "runs" / "temporal"
    u4d_methods = [f"{m}_s{s}" for m in ("u4d_most", "u4d_no_temporal") for s in (0, 1)]
    u4d_methods += [f"fusion_{v}_s0" for v in ("cascade", "add", "concat")]
    for name in u4d_methods:  # U4D's two stages together get the baseline's budget
        total = steps[str(runs / name / "stage1")] + steps[str(runs / name / "stage2")]
        assert total == steps[str(runs / "baseline_most_s0")] == steps[str(runs / "baseline_most_s1")] == 40
    fusions = {}
    for argv in made:
        if argv[0] == "train-diffusion" and "fusion_" in option(argv, "--out"):
            fusions[option(argv, "--out")] = next(a for a in argv if a.startswith("net.most_fusion="))
    assert sorted(set(fusions.values())) == ["net.most_fusion=add", "net.most_fusion=cascade", "net.most_fusion=concat"]
    no_temporal = [a for a in made if a[0] == "train-diffusion" and "u4d_no_temporal" in option(a, "--out")]
    assert len(no_temporal) == 4 and all("net.most=false" in a for a in no_temporal)

    floor = runs / "floor" / "sequences"
    assert sorted(p.name for p in floor.iterdir()) == [str(s) for s in range(88, 100)]
    table = json.loads((tmp / "results" / "temporal.json").read_text())
    assert set(table["methods"]) == {"u4d_most", "baseline_most", "u4d_no_temporal", "floor"}
    assert table["methods"]["u4d_most"]["seeds"] == 2 and table["methods"]["floor"]["seeds"] == 1
    assert set(table["fusion"]) == {"gating", "cascade", "add", "concat"}
    assert (runs / "gates_u4d_most_s0.json").read_text().strip() == "{}"

    (tmp / "calls.jsonl").unlink()
    run_queue("B", env)
    run_queue("A", env)
    again = calls(tmp / "calls.jsonl")
    assert [a[0] for a in again] == ["gates"]  # only the figure is redrawn; every run, bank and score is kept


def test_the_script_needs_a_core(queue_env):
    env, _ = queue_env
    env = {k: v for k, v in env.items() if k != "CORE"}
    result = subprocess.run(["bash", str(SCRIPT)], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode != 0 and "set CORE=A or CORE=B" in result.stderr
