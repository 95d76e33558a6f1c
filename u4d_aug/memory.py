"""What this machine can hold: sizes a user asks for are checked against its free memory before anything is
allocated, so that a typo (`num=1e8`, `model.width=1e4`, a 40 GiB file) is one line naming the setting rather
than an allocator traceback or a machine that swaps itself to a halt."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from u4d_aug.errors import InputError

if TYPE_CHECKING:
    import torch

MEMINFO = Path("/proc/meminfo")


def available_bytes(meminfo: Path = MEMINFO) -> int:
    """Memory a new allocation can take without swapping: Linux's MemAvailable, else free physical pages."""
    try:
        for line in meminfo.read_text(encoding="ascii").splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: no limit from us


def gib(nbytes: float) -> str:
    """Bytes as GiB with 1 decimal ('40.0 GiB')."""
    return f"{nbytes / 2**30:.1f} GiB"


def check_fits(nbytes: float, what: str, hint: str = "", available: int | None = None) -> None:
    """InputError when `what` would need more than the machine's available memory; `hint` says which setting."""
    free = available_bytes() if available is None else available
    if nbytes > free:
        raise InputError(
            f"{what} needs about {gib(nbytes)}, more than the {gib(free)} of memory available here"
            + (f"; {hint}" if hint else "")
        )


def training_bytes(build: Callable[[], torch.nn.Module]) -> int:
    """Bytes a net built by `build` takes in training: weights, gradients, two Adam moments and an EMA copy (5x its
    parameters and buffers), counted on the meta device, so nothing is allocated."""
    import torch

    with torch.device("meta"):
        net = build()
    tensors = [*net.parameters(), *net.buffers()]
    return 5 * sum(t.numel() * t.element_size() for t in tensors)


def check_net_fits(build: Callable[[], torch.nn.Module], what: str, hint: str) -> None:
    """InputError when the net `build` makes could not be trained in this machine's memory (`training_bytes`)."""
    check_fits(training_bytes(build), what, hint)
