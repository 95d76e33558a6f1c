"""Exponential moving average of the weights the samplers run with (u4d_aug/ema.py)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from u4d_aug.ema import EMA


def linear_pair() -> tuple[nn.Module, nn.Module]:
    torch.manual_seed(0)
    a = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    b = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    with torch.no_grad():
        for p in b.parameters():
            p.add_(1.0)
        b[1].running_mean.fill_(2.0)
    return a, b


def test_ema_decay_zero_copies_and_decay_one_keeps():
    a, b = linear_pair()
    ema = EMA(a, decay=0.0)
    ema.update(b)
    target = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    ema.copy_to(target)
    for p, q in zip(target.state_dict().values(), b.state_dict().values()):
        assert torch.equal(p, q)

    a, b = linear_pair()
    start = {k: v.clone() for k, v in a.named_parameters()}
    ema = EMA(a, decay=1.0)
    ema.update(b)
    ema.copy_to(a)
    for name, p in a.named_parameters():
        assert torch.equal(p, start[name])
    assert torch.equal(a[1].running_mean, b[1].running_mean)  # buffers are copied, not averaged


def test_ema_average_warmup_and_state_roundtrip():
    a, b = linear_pair()
    ema = EMA(a, decay=0.75, warmup_steps=1)
    assert ema.current_decay() == 0.0
    ema.update(a)  # warm-up: copy
    ema.update(b)  # 0.75 a + 0.25 b
    expected = {n: 0.75 * p + 0.25 * dict(b.named_parameters())[n] for n, p in a.named_parameters()}
    restored = EMA(b, decay=0.1)
    restored.load_state_dict(ema.state_dict())
    target = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    restored.copy_to(target)
    for name, p in target.named_parameters():
        assert torch.allclose(p, expected[name].detach(), atol=1e-6)
    assert restored.decay == 0.75 and restored.num_updates == 2
    with pytest.raises(ValueError, match="do not match"):
        EMA(nn.Linear(3, 4)).load_state_dict(ema.state_dict())
    with pytest.raises(ValueError, match="decay"):
        EMA(a, decay=1.5)


def test_warmup_copies_for_its_steps_then_averages():
    a, b = linear_pair()
    ema = EMA(a, decay=0.5, warmup_steps=2)
    decays = []
    for model in (b, a, b):  # two warm-up updates (the second copies a outright), then one average
        decays.append(ema.current_decay())
        ema.update(model)
    assert decays == [0.0, 0.0, 0.5] and ema.num_updates == 3
    weights_b = dict(b.named_parameters())
    for name, p in a.named_parameters():
        torch.testing.assert_close(ema.params[name], 0.5 * (p + weights_b[name]).detach())
    with pytest.raises(ValueError, match="warmup_steps must be >= 0"):
        EMA(a, warmup_steps=-1)


def test_the_shadow_and_its_state_dict_are_copies():
    a, b = linear_pair()
    ema = EMA(a, decay=1.0)
    state = ema.state_dict()
    with torch.no_grad():
        for p in a.parameters():
            p.mul_(3.0)  # training the model after the EMA was made
    for value in state["params"].values():
        value.zero_()  # editing a saved state
    ema.copy_to(b)
    assert b[0].weight.abs().sum() > 0
    torch.testing.assert_close(3.0 * b[0].weight, a[0].weight)  # the shadow still holds a's first weights
