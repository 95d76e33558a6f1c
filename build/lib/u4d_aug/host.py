"""What machine a timing was measured on (CPU model and family, clock, cores, threads, torch build).

Wall-clock figures on shared 2-core hosts differ by up to ~2x with the host behind them, so every benchmark json
and every seg-train run (OUT/hosts.jsonl) records this next to its times.
"""

from __future__ import annotations

import contextlib
import os
import platform
from pathlib import Path

import torch


def parse_cpuinfo(text: str) -> dict:
    """Vendor, model name, family/model numbers and MHz of the first processor block of /proc/cpuinfo text."""
    fields = {"vendor_id": "vendor", "model name": "cpu", "cpu family": "cpu_family", "model": "cpu_model"}
    out: dict = {}
    for line in text.split("\n\n")[0].splitlines():
        key, sep, value = line.partition(":")
        key, value = key.strip(), value.strip()
        if not sep:
            continue
        if key in fields:
            out[fields[key]] = int(value) if key in ("cpu family", "model") and value.isdigit() else value
        elif key == "cpu MHz":
            with contextlib.suppress(ValueError):
                out["mhz"] = round(float(value))
    return out


def host_info() -> dict:
    """This process's machine: /proc/cpuinfo fields (Linux), cores, torch threads and version, platform."""
    cpuinfo = Path("/proc/cpuinfo")
    info = parse_cpuinfo(cpuinfo.read_text()) if cpuinfo.is_file() else {}
    info.setdefault("cpu", platform.processor() or platform.machine())
    info.update(
        cores=os.cpu_count(),
        torch_threads=torch.get_num_threads(),
        torch=torch.__version__,
        cuda=torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        platform=platform.platform(),
    )
    return info
