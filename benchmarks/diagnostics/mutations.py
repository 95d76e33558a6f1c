"""Does a test fail when a headline feature breaks? Answer: the table this prints (mutation | test file(s) | caught)."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Literal, NamedTuple

REPO = Path(__file__).resolve().parents[2]
# not needed by the tests, and large or rebuilt: left out of each scratch copy
SKIPPED = (".git", "__pycache__", ".pytest_cache", ".ruff_cache", "*.egg-info")


class Mutation(NamedTuple):
    """One breakage: `before` -> `after` in the file `path` (kind "text", `before` found there exactly once), or the
    tensor named `before` of a shipped weights file zeroed with its hash fields kept (kind "zero_tensor")."""

    number: str  # the breakage's number in issue 72, deliverable 6 (a letter: a second way of making it)
    name: str
    path: str
    before: str
    after: str
    tests: tuple[str, ...]
    kind: Literal["text", "zero_tensor"] = "text"
    slow_tests: tuple[str, ...] = ()  # marked slow: run with --slow only


MUTATIONS = (
    Mutation(
        "1",
        "propagation drops the pin (pipeline)",
        "u4d_aug/pipeline.py",
        "motion=motion2, pin_known=pin_known)",
        "motion=motion2)",
        ("tests/u4d_aug/test_pipeline_pin.py",),
    ),
    Mutation(
        "1b",
        "propagation drops the pin (generate_bank)",
        "u4d_aug/generate.py",
        "pin_known=cfg.propagate_pin,",
        "pin_known=False,",
        ("tests/u4d_aug/test_pipeline_pin.py",),
    ),
    Mutation(
        "2",
        "a shipped tensor zeroed, its hashes kept",
        "weights/u4d.pt",
        "out_conv.weight",
        "",
        ("tests/u4d_aug/test_weights_hashes.py",),
        kind="zero_tensor",
    ),
    Mutation(
        "3",
        "burn-in signature without optim",
        "segmentation/experiment.py",
        'for key in ("mode", "out_dir"):',
        'for key in ("mode", "out_dir", "optim"):',
        ("tests/segmentation/test_experiment_burn_in.py",),
    ),
    Mutation(
        "4",
        "generate_bank skips stage 1's mean start",
        "u4d_aug/generate.py",
        "nets[name] = (MeanStart(",
        'nets[name] = (net, net_cfg) if name == "stage1" else (MeanStart(',
        ("tests/u4d_aug/test_mean_start_stage1.py",),
    ),
    Mutation(
        "4b",
        "the stage-1 sampler skips the mean start (pipeline)",
        "u4d_aug/pipeline.py",
        "if start is not None:",
        "if start is not None and task != STAGE1_TASK:",
        ("tests/u4d_aug/test_mean_start_stage1.py",),
    ),
    Mutation(
        "5",
        "the unlabeled stream loads its last source (a bank) whatever source it draws",
        "segmentation/semi.py",
        "item = self.sources[source][index]",
        "item = self.sources[-1][index % len(self.sources[-1])]",
        ("tests/segmentation/test_semi_stream.py",),
        slow_tests=("tests/segmentation/test_experiment_banks.py",),
    ),
)


def check(mutation: Mutation, root: Path = REPO) -> str | None:
    """Why `mutation` no longer applies to the checkout at `root` (None: it applies)."""
    path = root / mutation.path
    if not path.is_file():
        return f"{mutation.path}: not found"
    missing = [test for test in (*mutation.tests, *mutation.slow_tests) if not (root / test).is_file()]
    if missing:
        return f"test files not found: {', '.join(missing)}"
    if mutation.kind == "text":
        count = path.read_text(encoding="utf-8").count(mutation.before)
        return None if count == 1 else f"{mutation.path}: its 'before' text occurs {count} times, not once"
    import torch  # only the weights mutation needs it

    tensor = torch.load(path, weights_only=True)["model"].get(mutation.before)
    if tensor is None or not bool(tensor.float().abs().sum() > 0):
        return f"{mutation.path}: no non-zero tensor {mutation.before}"
    return None


def apply(mutation: Mutation, root: Path) -> None:
    """Break the one file of `mutation` in the checkout at `root` (a scratch copy)."""
    problem = check(mutation, root)
    if problem is not None:
        raise ValueError(f"mutation {mutation.number} ({mutation.name}): {problem}")
    path = root / mutation.path
    if mutation.kind == "text":
        path.write_text(path.read_text(encoding="utf-8").replace(mutation.before, mutation.after), encoding="utf-8")
        return
    import torch

    state = torch.load(path, weights_only=True)
    state["model"][mutation.before] = torch.zeros_like(state["model"][mutation.before])
    torch.save(state, path)  # hash and weights_hash as they were


def scratch_copy(folder: Path) -> Path:
    """The checkout (working tree, without .git and caches) copied to folder/repo; symlinked data stays a link."""
    return Path(shutil.copytree(REPO, folder / "repo", symlinks=True, ignore=shutil.ignore_patterns(*SKIPPED)))


def run_tests(root: Path, tests: tuple[str, ...], slow: bool) -> int:
    """pytest's exit code for `tests` in the checkout at `root`, whose packages shadow the installed ones."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    probe = "import segmentation, u4d_aug; print(u4d_aug.__file__); print(segmentation.__file__)"
    where = subprocess.run([sys.executable, "-c", probe], cwd=root, env=env, capture_output=True, text=True, check=True)
    if not all(Path(line).resolve().is_relative_to(root.resolve()) for line in where.stdout.split()):
        raise RuntimeError(f"the packages resolve outside the scratch copy {root}: {where.stdout.split()}")
    marker = [] if slow else ["-m", "not slow"]
    command = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:xdist", *marker, *tests]
    return subprocess.run(command, cwd=root, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode


def verdict(code: int) -> str:
    """pytest exit code -> caught: 1 (a test failed) yes, 0 (all passed) no, else what went wrong."""
    return {0: "no", 1: "yes", 5: "no tests ran"}.get(code, f"error (pytest exit {code})")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", nargs="+", help="the mutations to run, by number (1, 1b, 2, ...; default all)")
    parser.add_argument("--slow", action="store_true", help="also run the slow end-to-end test files")
    parser.add_argument("--control", action="store_true", help="first run every test file on an unmutated copy")
    parser.add_argument("--list", action="store_true", help="list the mutations and whether each applies; run none")
    args = parser.parse_args()
    chosen = [m for m in MUTATIONS if not args.only or m.number in args.only]
    if args.list:
        for mutation in chosen:
            print(f"{mutation.number}. {mutation.name}: {mutation.path}: {check(mutation) or 'applies'}")
        return 0
    rows = []
    if args.control:
        tests = tuple(dict.fromkeys(t for m in chosen for t in (*m.tests, *(m.slow_tests if args.slow else ()))))
        with tempfile.TemporaryDirectory(prefix="u4d_mutation_") as folder:
            code = run_tests(scratch_copy(Path(folder)), tests, args.slow)
        rows.append(
            (
                "0. none (control: all should pass)",
                ", ".join(tests),
                "passed" if code == 0 else f"FAILED (pytest exit {code})",
            )
        )
    for mutation in chosen:
        tests = (*mutation.tests, *(mutation.slow_tests if args.slow else ()))
        with tempfile.TemporaryDirectory(prefix="u4d_mutation_") as folder:
            root = scratch_copy(Path(folder))
            apply(mutation, root)
            caught = verdict(run_tests(root, tests, args.slow))
        rows.append((f"{mutation.number}. {mutation.name} ({mutation.path})", ", ".join(tests), caught))
        print(" | ".join(rows[-1]), file=sys.stderr, flush=True)
    header = ("mutation", "test file(s)", "caught")
    print("| " + " | ".join(header) + " |\n|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(row) + " |")
    return 0 if all(row[2] in ("yes", "passed") for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
