"""u4d_aug.memory: sizes checked against the machine's available memory."""

from __future__ import annotations

import pytest

from u4d_aug.errors import InputError
from u4d_aug.memory import available_bytes, check_fits, check_net_fits, gib, training_bytes


def test_available_bytes_reads_memavailable(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       24000000 kB\nMemFree:  100 kB\nMemAvailable:   2097152 kB\n")
    assert available_bytes(meminfo) == 2 * 2**30
    assert 0 < available_bytes() < 1 << 62  # this machine's, from /proc/meminfo or sysconf
    assert available_bytes(tmp_path / "missing") > 0  # falls back to sysconf


def test_check_fits_names_what_and_how_much():
    check_fits(2**30, "a scan", available=2 * 2**30)
    with pytest.raises(InputError, match=r"scan.bin needs about 40.0 GiB, more than the 2.0 GiB .*; is it a scan\?"):
        check_fits(40 * 2**30, "scan.bin", "is it a scan?", available=2 * 2**30)
    assert gib(1.5 * 2**30) == "1.5 GiB"


def test_training_bytes_counts_a_net_on_the_meta_device_without_allocating_it():
    import torch

    def build() -> torch.nn.Module:
        return torch.nn.Sequential(torch.nn.Linear(10, 20), torch.nn.BatchNorm1d(20))

    params = 10 * 20 + 20 + 20 + 20  # linear weight, bias; batch-norm weight, bias
    buffers = 20 + 20  # running mean, var (num_batches_tracked: one int64)
    assert training_bytes(build) == 5 * (4 * (params + buffers) + 8)
    huge = lambda: torch.nn.Linear(10**6, 10**6)  # noqa: E731 - 4 TB of weights: only counted, never allocated
    assert training_bytes(huge) > 2**42
    with pytest.raises(InputError, match="the net of model.* needs about .* GiB.*; reduce model.width"):
        check_net_fits(huge, "the net of model.*", "reduce model.width")
