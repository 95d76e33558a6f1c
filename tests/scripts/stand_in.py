"""Stand-ins for `u4d` and the benchmark interpreter, so that the queue scripts (scripts/*_queue.sh) run in seconds:
each call is recorded and leaves behind what the real command would (a run's last log step, a complete bank manifest,
an evaluation.json, a model file), and `check_call` replays a recorded call through the real parsers and config
loaders, so a typo in a flag, a config key or a preset path fails the test instead of a night of runs."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from segmentation.config import SegTrainConfig
from segmentation.experiment import ExperimentConfig, run_config
from u4d_aug.cli import delegated_parser
from u4d_aug.cmdline import parse_command_line, split_verbosity
from u4d_aug.config import load_config
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.generate import GenerateConfig
from u4d_aug.metrics.extractors import ExtractorConfig
from u4d_aug.train import DiffusionTrainConfig, split_stage_override

FAKE_U4D = """#!{python}
import json, os, sys
from pathlib import Path
import yaml
argv = sys.argv[1:]
with open(os.environ["FAKE_LOG"], "a") as log:
    log.write(json.dumps(argv) + "\\n")
out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else None
overrides = dict(a.split("=", 1) for a in argv if "=" in a and not a.startswith("-"))
command = argv[0]
if command in ("simulate", "seg-predict"):
    out.mkdir(parents=True, exist_ok=True)
elif command == "seg-train":
    out.mkdir(parents=True, exist_ok=True)
    (out / "model.pt").write_bytes(b"")
elif command == "seg-eval":
    print("{{}}")
elif command == "train-diffusion":
    steps = int(overrides.get("steps") or yaml.safe_load(open(argv[1]))["steps"])
    out.mkdir(parents=True, exist_ok=True)
    (out / "log.jsonl").write_text(json.dumps({{"step": steps, "time": 60.0 * steps}}) + "\\n")
elif command == "generate":
    out.mkdir(parents=True, exist_ok=True)
    (out / "manifest.json").write_text(json.dumps({{"complete": True}}))
elif command == "train-extractor":
    folder = Path(overrides["out_dir"])
    folder.mkdir(parents=True, exist_ok=True)
    (folder / (argv[1] + ".pt")).write_bytes(b"")
elif command == "evaluate":
    out.mkdir(parents=True, exist_ok=True)
    value = float(len(str(out)) % 7 + 1)
    bank = {{"ttce": {{"3": value, "4": value + 1}}, "ctc": {{str(k): value * k for k in range(1, 5)}}}}
    result = {{"table1": {{"frd": {{"value": 100 * value}}}}, "table2": {{"bank": bank}}}}
    (out / "evaluation.json").write_text(json.dumps(result))
elif command == "gates":
    print("{{}}")
elif command == "export-weights":
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(b"")
elif command == "experiment":  # a record per arm, backbone and seed asked for, where the config keeps them
    config = yaml.safe_load(open(argv[1]))
    records = overrides.get("records_dir", config.get("records_dir"))
    seeds = yaml.safe_load(overrides.get("seeds", "null")) or config["seeds"]
    backbones = yaml.safe_load(overrides.get("backbones", "null")) or config["backbones"]
    arms = []
    for a in argv[argv.index("--arms") + 1 :] if "--arms" in argv else []:
        if a.startswith("-"):
            break
        arms.append(a)
    for arm in arms if records else []:
        for backbone in backbones:
            for seed in seeds:
                path = Path(records) / arm / backbone / f"seed{{seed}}.json"
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps({{"format": 1}}))
else:
    sys.exit("stand-in u4d: unknown command " + command)
"""

FAKE_PY = """#!{python}
import json, os, sys
from pathlib import Path
argv = sys.argv[1:]
with open(os.environ["FAKE_LOG"], "a") as log:
    log.write(json.dumps(["py", *argv]) + "\\n")
if "--out" in argv:
    out = Path(argv[argv.index("--out") + 1])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("{{}}")
"""

CONFIGS = {  # commands that take CONFIG [key=value ...] and the dataclass their run_* function loads it into
    "simulate": SimConfig,
    "seg-train": SegTrainConfig,
    "train-diffusion": DiffusionTrainConfig,
    "generate": GenerateConfig,
    "train-extractor": ExtractorConfig,
    "experiment": ExperimentConfig,
}


def stand_in_env(tmp_path: Path, **extra: str) -> dict[str, str]:
    """Environment with the stand-in `u4d` first on PATH, PY set to the stand-in interpreter, calls logged."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    for name, text in (("u4d", FAKE_U4D), ("py", FAKE_PY)):
        path = bin_dir / name
        path.write_text(text.format(python=sys.executable))
        path.chmod(0o755)
    return {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        "FAKE_LOG": str(tmp_path / "calls.jsonl"),
        "PY": str(bin_dir / "py"),
        **extra,
    }


def run_both(script: Path, cwd: Path, env: dict) -> None:
    """A queue script as CORE=A and CORE=B side by side, as on a 2-core machine (each waits for what the other
    writes); both must exit 0."""
    procs = [
        subprocess.Popen(
            ["bash", str(script)],
            cwd=cwd,
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


def recorded_calls(tmp_path: Path) -> list[list[str]]:
    """Every call so far, in order: `u4d` argv, or ["py", script, args...] for the interpreter."""
    log = tmp_path / "calls.jsonl"
    return [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []


def check_call(argv: list[str], cwd: Path) -> tuple[argparse.Namespace, Any]:
    """Parse one recorded `u4d` call with the command's real parser and load its config with its overrides (paths
    relative to cwd); returns (args, config or None). Parser errors exit, loader errors raise: either fails a test."""
    parser, _ = delegated_parser(argv[0])
    args = parse_command_line(parser, split_verbosity(argv[1:])[0])  # as u4d_aug.cli.main does
    cls = CONFIGS.get(argv[0])
    if cls is None:
        return args, None
    overrides = [*(getattr(args, "set_overrides", None) or []), *(getattr(args, "overrides", None) or [])]
    if argv[0] == "train-diffusion":
        overrides = split_stage_override(overrides)
    config = args.config if args.config is None or Path(args.config).is_absolute() else cwd / args.config
    cfg = load_config(cls, config, overrides)
    if argv[0] == "experiment":  # every arm asked for exists and its runs' configs load
        names = [arm.name for arm in cfg.arms]
        assert set(args.arms or names) <= set(names), (args.arms, names)
        previous = Path.cwd()
        os.chdir(cwd)  # the experiment's base config is relative to the checkout
        try:
            for arm in cfg.arms:
                if arm.name in (args.arms or names):
                    for backbone in cfg.backbones:
                        for seed in cfg.seeds:
                            run_config(cfg, arm, backbone, seed)
        finally:
            os.chdir(previous)
    return args, cfg
