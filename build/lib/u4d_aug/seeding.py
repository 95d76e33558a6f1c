"""Seeds derived from integers, so that what a run draws at step s depends only on (seed, stream, step, rank)."""

from __future__ import annotations

import numpy as np


def derived_seed(*parts: int) -> int:
    """A 63-bit seed hashed from non-negative integers (numpy SeedSequence; no global state)."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1, np.uint64)[0] >> np.uint64(1))
