"""u4d_aug.validate: finite config numbers, positive sizes, plain names, finite losses, weights that fit the net;
one line naming the key."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest
import torch

from u4d_aug.errors import InputError
from u4d_aug.validate import (
    NonFiniteLossError,
    check_finite_config,
    check_finite_loss,
    check_plain_name,
    check_positive,
    check_state_fits,
    nonfinite_keys,
    state_mismatches,
)


@dataclass
class Inner:
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.99)


@dataclass
class Outer:
    inner: Inner = field(default_factory=Inner)
    steps: int = 3
    extra: dict = field(default_factory=dict)


def test_nonfinite_keys_walk_dataclasses_dicts_and_lists():
    assert nonfinite_keys(Outer()) == []
    cfg = Outer(Inner(float("inf"), (0.9, float("nan"))), extra={"w": [1.0, float("-inf")]})
    assert nonfinite_keys(cfg) == ["inner.lr", "inner.betas[1]", "extra.w[1]"]
    with pytest.raises(InputError, match=r"key 'inner.lr' must be a finite number, got inf"):
        check_finite_config(cfg)
    with pytest.raises(InputError, match=r"key 'optim.betas\[1\]' must be a finite number, got nan"):
        check_finite_config(Inner(1.0, (0.9, float("nan"))), "optim.")


def test_check_positive_names_the_key():
    check_positive(Outer(), "steps", "inner.lr")
    with pytest.raises(InputError, match="key 'steps' must be > 0, got 0"):
        check_positive(Outer(steps=0), "steps")
    check_positive(Outer(steps=0), "steps", allow_zero=True)
    with pytest.raises(InputError, match="key 'x.steps' must be >= 0, got -1"):
        check_positive(Outer(steps=-1), "steps", allow_zero=True, prefix="x.")


@pytest.mark.parametrize("name", ["../../escaped", "a/b", "a\\b", "..", ".", "", " ", "x\0y"])
def test_plain_names_refuse_paths(name):
    with pytest.raises(InputError, match="must be a plain name"):
        check_plain_name(name, "arm name")


def test_plain_names_pass():
    assert check_plain_name("mt-lasermix_u4d.v2", "arm name") == "mt-lasermix_u4d.v2"


def test_finite_loss_guard_names_the_step():
    check_finite_loss(torch.tensor(1.5), 7, torch.tensor(2.0))
    with pytest.raises(NonFiniteLossError, match="training step 7: the loss is nan"):
        check_finite_loss(torch.tensor(float("nan")), 7)
    with pytest.raises(NonFiniteLossError, match="training step 8: the gradient norm is inf"):
        check_finite_loss(torch.tensor(1.0), 8, torch.tensor(float("inf")))
    assert issubclass(NonFiniteLossError, InputError)  # exit code 2 through the CLI


def test_state_mismatches_name_missing_foreign_reshaped_and_non_tensors():
    net = torch.nn.Linear(3, 2)
    expected = net.state_dict()
    assert state_mismatches(dict(expected), expected) == []
    wrong = {"weight": torch.zeros(2, 4), "bias": "x", "extra": torch.zeros(1)}
    problems = state_mismatches(wrong, expected)
    assert problems == [
        "extra: not in this net",
        "weight: shape (2, 4) here, (2, 3) in the net this config builds",
        "bias: a str, not a tensor",
    ]
    assert state_mismatches([1, 2], expected) == ["a list where a name -> tensor mapping belongs"]
    with pytest.raises(
        InputError,
        match=r"^ckpt.pt: its weights do not fit the net \(weight: missing; bias: missing\); "
        r"the config changed: width 3 -> 4$",
    ):
        check_state_fits({}, expected, "ckpt.pt", "the config changed: width 3 -> 4")
