"""benchmarks/peak_memory.py: the peak-RSS window sees an allocation; run_case returns a child's json or raises."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tiny_nets import REPO, load_script

peak_memory = load_script("peak_memory")


def test_memory_window_sees_a_64_mb_allocation():
    before = peak_memory.start_memory_window()
    block = np.ones(64 * 2**20 // 8)  # 64 MB, touched
    assert block.sum() == block.size
    del block
    assert before > 0 and peak_memory.peak_mb() - before >= 60


def test_run_case_returns_the_last_json_line_of_the_child(tmp_path):
    script = tmp_path / "child.py"
    script.write_text(
        "import json, os, sys\n"
        "print('noise')\n"
        "print(json.dumps({'argv': sys.argv[1:], 'omp': os.environ['OMP_WAIT_POLICY'], "
        "'cwd': os.getcwd(), 'path': os.environ['PYTHONPATH']}))\n"
    )
    result = peak_memory.run_case(script, ["--a", "1"], "toy case")
    assert result["argv"] == ["--a", "1"] and result["omp"] == "PASSIVE" and result["cwd"] == str(REPO)
    assert result["path"].split(":")[0] == str(REPO)


def test_run_case_raises_with_the_child_stderr(tmp_path):
    script = tmp_path / "fail.py"
    script.write_text("import sys\nsys.exit('child broke')\n")
    with pytest.raises(RuntimeError, match="toy case failed:\nchild broke"):
        peak_memory.run_case(script, [], "toy case")
