"""segmentation.optimizer: warm-up + cosine learning rate (annealed to the budget too), AdamW parameter groups."""

from __future__ import annotations

import itertools

import pytest

from segmentation.config import SegOptimConfig, SegTrainConfig
from segmentation.optimizer import learning_rate
from tests.tiny_nets import SEG_TINY as TINY
from u4d_aug.config import load_config
from u4d_aug.errors import InputError


def test_learning_rate_warmup_then_cosine():
    cfg = SegOptimConfig(lr=1.0, warmup_steps=10, steps=110, min_lr_ratio=0.1)
    assert learning_rate(0, cfg) == pytest.approx(0.1)
    assert learning_rate(9, cfg) == pytest.approx(1.0)
    assert learning_rate(10, cfg) == pytest.approx(1.0)
    assert learning_rate(60, cfg) == pytest.approx(0.55)  # half-way down the cosine
    assert learning_rate(110, cfg) == pytest.approx(0.1)
    lrs = [learning_rate(s, cfg) for s in range(10, 111)]
    assert all(a >= b for a, b in itertools.pairwise(lrs))


def test_learning_rate_annealed_to_the_budget_follows_the_larger_progress():
    cfg = SegOptimConfig(lr=1.0, warmup_steps=10, steps=110, min_lr_ratio=0.1, anneal_to="budget")
    assert learning_rate(60, cfg, 0.0) == learning_rate(60, cfg) == pytest.approx(0.55)  # steps ahead of time
    assert learning_rate(60, cfg, 0.25) == pytest.approx(0.55)
    assert learning_rate(20, cfg, 0.5) == pytest.approx(0.55)  # time ahead of steps: half-way down anyway
    assert learning_rate(20, cfg, 1.0) == pytest.approx(0.1)  # budget used: min lr
    assert learning_rate(5, cfg, 1.0) == pytest.approx(0.6)  # warm-up is counted in steps only
    with pytest.raises(InputError, match="anneal_to=budget needs a wall-clock budget"):
        load_config(SegTrainConfig, TINY, ["optim.anneal_to=budget"])
    with pytest.raises(InputError, match="anneal_to"):
        load_config(SegTrainConfig, TINY, ["optim.anneal_to=time", "max_minutes=1"])
