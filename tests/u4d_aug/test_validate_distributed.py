"""Under torchrun (2 CPU processes, gloo) a NaN loss on one rank stops every rank with the one-line error, instead
of leaving the other rank waiting in the gradient all-reduce until the process group times out."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

SCRIPT = """
import sys, torch
from u4d_aug.distributed import all_reduce_sum, barrier, cleanup, init_distributed
from u4d_aug.validate import NonFiniteLossError, check_finite_loss
info = init_distributed("cpu")
bad_rank = int(sys.argv[1])
for step in range(1, 4):
    loss = torch.tensor(float("nan") if (info.rank == bad_rank and step == 2) else 1.0)
    try:
        check_finite_loss(loss, step)
    except NonFiniteLossError as exc:
        with open(f"rank{info.rank}.txt", "w") as out:  # a file per rank: torchrun's shared stdout may lose lines
            out.write(f"rank {info.rank} stopped: {exc}")
        barrier()  # both have printed before either exits (torchrun stops the others when one rank fails)
        cleanup()
        sys.exit(3)
    all_reduce_sum(torch.ones(1))  # stands for backward's gradient all-reduce, which a lone rank would wait in
with open(f"rank{info.rank}.txt", "w") as out:
    out.write(f"rank {info.rank} finished")
cleanup()
"""


def run_two_ranks(tmp_path: Path, bad_rank: int) -> subprocess.CompletedProcess:
    script = tmp_path / "nan_rank.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--standalone", str(script)]
    return subprocess.run(cmd + [str(bad_rank)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)


def test_nan_on_one_rank_stops_both(tmp_path):
    result = run_two_ranks(tmp_path, bad_rank=1)
    assert result.returncode != 0
    said = [(tmp_path / f"rank{rank}.txt").read_text() for rank in (0, 1)]
    assert said[1].startswith("rank 1 stopped: training step 2: the loss is nan on rank 1;")
    assert said[0].startswith("rank 0 stopped: training step 2: the loss is not finite on rank 1;")


def test_finite_losses_run_through(tmp_path):
    result = run_two_ranks(tmp_path, bad_rank=-1)
    assert result.returncode == 0, result.stderr[-2000:]
    assert [(tmp_path / f"rank{rank}.txt").read_text() for rank in (0, 1)] == ["rank 0 finished", "rank 1 finished"]
