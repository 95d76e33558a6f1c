"""u4d_aug.host: the machine record written beside timings."""

from __future__ import annotations

import os

import torch

from u4d_aug.host import host_info, parse_cpuinfo

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 1
model name\t: AMD EPYC 7B13
cpu MHz\t\t: 2445.406
flags\t\t: fpu avx2 vaes

processor\t: 1
vendor_id\t: GenuineIntel
model name\t: another core
"""


def test_parse_cpuinfo_reads_the_first_processor_block():
    assert parse_cpuinfo(CPUINFO) == {
        "vendor": "AuthenticAMD",
        "cpu_family": 25,
        "cpu_model": 1,
        "cpu": "AMD EPYC 7B13",
        "mhz": 2445,
    }


def test_parse_cpuinfo_tolerates_missing_and_odd_fields():
    assert parse_cpuinfo("") == {}
    assert parse_cpuinfo("model name\t: ARMv8\ncpu MHz\t: n/a\nmodel\t: 0x1\n") == {"cpu": "ARMv8", "cpu_model": "0x1"}


def test_host_info_describes_this_process():
    info = host_info()
    assert info["cores"] == os.cpu_count()
    assert info["torch"] == torch.__version__ and info["torch_threads"] == torch.get_num_threads()
    assert isinstance(info["cpu"], str) and info["cpu"]
    assert info["cuda"] is None or isinstance(info["cuda"], str)
