"""Shared fixtures: the real-scan folder beside the checkout, tiny seeded generators, one intra-op thread, the toy
SemanticKITTI root, tiny diffusion checkpoints that several test modules read and a machine without installed nets."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.tiny_nets import TINY, TINY_MOST, save_checkpoint, save_random_checkpoint
from tests.tiny_worlds import REAL_ROOT, write_toy_root
from u4d_aug import progress, weights_store
from u4d_aug.cmdline import LOGGERS
from u4d_aug.weights_store import WEIGHTS_ENV

STAGES = ("stage1", "stage2", "baseline")

# Tiny tensors gain nothing from intra-op threads, and spinning OpenMP threads slow everything down when the
# 2 cores are shared; one thread keeps the suite fast and its timings steady.
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    """Every test starts on one thread, whatever the test before it (or the code it ran) set."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def reset_project_logging() -> None:
    """The project's loggers at their defaults (no level, no stderr handler) and progress bars on."""
    for name in LOGGERS:
        logging.getLogger(name).setLevel(logging.NOTSET)
        logging.getLogger(name).handlers[:] = []
    progress.set_quiet(False)


@pytest.fixture(autouse=True)
def project_log_levels() -> Iterator[None]:
    """Every test starts and ends with the project's logging at its defaults, whatever a CLI call set: a module
    fixture's `--quiet` runs before any per-test fixture and would otherwise hide the INFO records a test asserts."""
    reset_project_logging()
    yield
    reset_project_logging()


@pytest.fixture(scope="session")
def real_root() -> Path:
    """../shared/data/real, or skip: the real scans are research data that stay outside the repository."""
    if not (REAL_ROOT / "semantickitti" / "sequences" / "00" / "velodyne").is_dir():
        pytest.skip(f"real scans not found at {REAL_ROOT} (the ../shared/data/real folder beside the checkout)")
    return REAL_ROOT


@pytest.fixture(scope="session")
def kitti_root(real_root: Path) -> Path:
    """SemanticKITTI-layout root with seq 00 frames 0-5 (labels for 0-2), calib, poses, times."""
    return real_root / "semantickitti"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(0)


@pytest.fixture(scope="module")
def toy_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The toy SemanticKITTI root (tests/tiny_worlds.py), one per module: training runs may write a split file."""
    return write_toy_root(tmp_path_factory.mktemp("toy"))


@pytest.fixture(scope="session")
def untrained_checkpoints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Untrained tiny checkpoints of the three stages (EMA = initial weights; seeds 0, 1, 2)."""
    root = tmp_path_factory.mktemp("ckpt")
    return {
        stage: save_checkpoint(root / f"{stage}.pt", TINY, (f"diffusion.stage={stage}", f"seed={seed}"))
        for seed, stage in enumerate(STAGES)
    }


@pytest.fixture(scope="session")
def untrained_sequence_checkpoints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Untrained tiny 2-frame MoST checkpoints (configs/u4d/tiny_most.yaml) of the three stages."""
    root = tmp_path_factory.mktemp("ckpt_most")
    return {
        stage: save_checkpoint(root / f"{stage}.pt", TINY_MOST, (f"diffusion.stage={stage}", f"seed={seed}"))
        for seed, stage in enumerate(STAGES)
    }


@pytest.fixture(scope="session")
def random_ema_checkpoints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Tiny checkpoints of the three stages: random EMA weights, zero raw weights (`save_random_checkpoint`)."""
    root = tmp_path_factory.mktemp("ckpt_random_ema")
    return {stage: save_random_checkpoint(root / f"{stage}.pt", stage) for stage in STAGES}


@pytest.fixture
def no_installed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A machine with no checkout weights/, an empty user cache and no U4D_WEIGHTS (a wheel before `install`)."""
    monkeypatch.chdir(tmp_path)  # not the checkout, whose weights/NAME.pt exist as written
    monkeypatch.setattr(weights_store, "CHECKOUT_DIR", tmp_path / "no_checkout" / "weights")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv(WEIGHTS_ENV, "")  # recorded, so what main sets is undone
    return tmp_path
