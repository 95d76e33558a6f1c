"""u4d_aug.errors: bad input as a one-line error and exit code 2, also from the benchmark scripts."""

import subprocess
import sys

import pytest

from tests.tiny_nets import REPO
from u4d_aug.errors import InputError, exit_code_of


def test_exit_code_of_passes_the_code_through_and_turns_input_errors_into_2(capsys):
    assert exit_code_of(lambda argv: len(argv), ["a", "b", "c"]) == 3  # the run's own code
    assert exit_code_of(lambda argv: 0) == 0

    def bad(argv):
        raise InputError("cfg.yaml: key 'optim.lr' must be a number")

    assert exit_code_of(bad, []) == 2
    assert capsys.readouterr().err == "error: cfg.yaml: key 'optim.lr' must be a number\n"


def test_exit_code_of_lets_other_errors_through():
    def broken(argv):
        raise RuntimeError("a bug, not bad input")

    with pytest.raises(RuntimeError):
        exit_code_of(broken, [])


@pytest.mark.parametrize(
    ("script", "args", "names"),
    [
        ("diagnostics/bench_logit_bias.py", ["--classes", "lorry"], "--classes"),
        (
            "diagnostics/plot_seg_errors.py",
            ["--sequence", "00", "--frame", "0", "--focus", "lorry", "--out", "x.png"],
            "--focus",
        ),
    ],
)
def test_benchmark_scripts_report_bad_input_in_one_line(tmp_path, script, args, names):
    cmd = [sys.executable, str(REPO / "benchmarks" / script), str(tmp_path / "model.pt"), str(tmp_path), *args]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {names}") and "'lorry'" in lines[0]


@pytest.mark.parametrize(
    ("command", "args"),
    [
        ("seg-train", ["{missing}"]),
        ("seg-eval", ["{missing}", "{tmp}"]),
        ("seg-predict", ["{missing}", "{tmp}", "--out", "{tmp}/probs"]),
        ("experiment", ["{missing}"]),
        ("train-diffusion", ["{missing}"]),
        ("generate", ["{missing}", "--out", "{tmp}/bank"]),
    ],
)
def test_torchrun_commands_report_a_missing_file_in_one_line(tmp_path, capsys, command, args):
    """The commands run under `torchrun ... -m u4d_aug.cli COMMAND` (the one launch path) fail in one line."""
    from u4d_aug.cli import main

    missing = tmp_path / "nowhere.yaml"
    argv = [a.format(missing=missing, tmp=tmp_path) for a in args]
    assert main([command, *argv]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "nowhere.yaml" in lines[0]
