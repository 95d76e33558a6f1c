"""--quiet turns every progress bar off; without it a bar is drawn where the command asks for one."""

from __future__ import annotations

import subprocess
import sys

from u4d_aug import progress
from u4d_aug.cmdline import configure_logging


def test_quiet_disables_bars_whatever_the_call_asks():
    configure_logging(30)  # WARNING: --quiet (tests/conftest.py resets logging after each test)
    assert progress.progress_bar(range(3), enabled=True).disable
    configure_logging(20)  # INFO: the default
    assert not progress.progress_bar(range(3), enabled=True).disable
    assert progress.progress_bar(range(3), enabled=False).disable  # --no-progress still wins


def test_quiet_simulate_draws_no_bar(tmp_path):
    def simulate(out, *flags):
        command = [sys.executable, "-m", "u4d_aug.cli", "simulate", "--out", str(out), "--sequences", "1"]
        command += ["--frames", "1", "--seed", "0", "--config", "sim/tiny", *flags]
        return subprocess.run(command, capture_output=True, text=True, timeout=300)

    loud, quiet = simulate(tmp_path / "a"), simulate(tmp_path / "b", "--quiet")
    assert loud.returncode == quiet.returncode == 0
    assert "simulate: 100%" in loud.stderr and "%|" not in quiet.stderr
    assert "wrote 1 frames" in quiet.stdout  # results still go to stdout
