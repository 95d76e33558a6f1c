"""Seeds derived from integers (u4d_aug/seeding.py): a pure function of its parts, 63 bits, one golden number."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from u4d_aug.seeding import derived_seed


def test_golden_number_and_the_seed_sequence_it_comes_from():
    assert derived_seed(1, 2, 3, 0) == 6498626229777268288
    state = int(np.random.SeedSequence([1, 2, 3, 0]).generate_state(1, np.uint64)[0])
    assert derived_seed(1, 2, 3, 0) == state >> 1  # the top 63 bits: fits torch's and numpy's signed seeds


def test_same_parts_same_seed_other_parts_other_seeds():
    assert derived_seed(7, 1, 10, 0) == derived_seed(7, 1, 10, 0)
    seeds = {derived_seed(7, stream, step, rank) for stream in (1, 2) for step in range(50) for rank in range(4)}
    assert len(seeds) == 2 * 50 * 4  # every stream, step and rank draws its own numbers
    assert derived_seed(1, 2) != derived_seed(2, 1)  # the order of the parts matters
    assert all(0 <= seed < 2**63 for seed in seeds)


def test_a_derived_seed_starts_a_torch_generator_reproducibly():
    a = torch.randn(4, generator=torch.Generator().manual_seed(derived_seed(0, 2, 5, 1)))
    b = torch.randn(4, generator=torch.Generator().manual_seed(derived_seed(0, 2, 5, 1)))
    c = torch.randn(4, generator=torch.Generator().manual_seed(derived_seed(0, 2, 6, 1)))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_negative_parts_are_refused():
    with pytest.raises(ValueError, match="non-negative"):
        derived_seed(3, -1)
