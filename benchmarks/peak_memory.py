"""Peak resident memory of one benchmark case, and the subprocess runner that gives every case its own process.

The kernel's peak-RSS mark is reset (`5` written to /proc/self/clear_refs) right before a case; the memory the
case adds is VmHWM at its end minus VmRSS at the reset. tracemalloc does not see torch's CPU allocations.
Without /proc (not Linux) it falls back to ru_maxrss, whose earlier peaks then hide smaller later ones.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _status_mb(field: str) -> float | None:
    """VmRSS / VmHWM of this process from /proc/self/status in MB, None where unavailable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def start_memory_window() -> float:
    """Reset the kernel's peak-RSS mark and return the current RSS in MB (ru_maxrss without /proc)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        current = _status_mb("VmRSS")
        if current is not None:
            return current
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def peak_mb() -> float:
    """Peak RSS since the last reset (VmHWM), else ru_maxrss (KB on Linux), in MB."""
    peak = _status_mb("VmHWM")
    return peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_case(script: str | Path, argv: list[str], what: str) -> dict:
    """Run `python SCRIPT ARGV` in its own process (this checkout first on the path, passive OpenMP waits).

    Returns the json dict the child prints on its last stdout line; a failed child raises with its stderr.
    Spin-waiting OpenMP threads distort small ops on a shared machine, hence OMP_WAIT_POLICY=PASSIVE.
    """
    pythonpath = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", PYTHONPATH=pythonpath)
    done = subprocess.run(
        [sys.executable, str(script), *argv], capture_output=True, text=True, env=env, check=False, cwd=REPO
    )
    if done.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])
