"""Shared fixtures: the real-scan folder beside the checkout, tiny seeded generators."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

# Tiny tensors gain nothing from intra-op threads, and spinning OpenMP threads slow everything down when the
# 2 cores are shared; one thread keeps the suite fast and its timings steady.
torch.set_num_threads(1)

# ../shared/data/real beside the checkout; U4D_REAL_DATA points elsewhere (a git worktree one folder deeper)
REAL_ROOT = Path(os.environ.get("U4D_REAL_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data" / "real")


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
