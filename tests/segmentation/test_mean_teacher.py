"""segmentation.mean_teacher: EMA ends (decay 0 copies, 1 keeps), pseudo-label threshold, MSE consistency."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from segmentation.config import SegTrainConfig, SemiConfig
from segmentation.mean_teacher import (
    MeanTeacherConfig,
    consistency_loss,
    consistency_rampup,
    copy_buffers,
    ema_update,
    make_teacher,
    mean_view_probs,
    pseudo_labels,
    scan_views,
    teacher_mode,
    total_loss,
)
from u4d_aug.config import load_config
from u4d_aug.errors import InputError


def _net(seed: int) -> nn.Module:
    net = nn.Sequential(nn.Linear(4, 8), nn.BatchNorm1d(8), nn.ReLU(), nn.Dropout(0.3), nn.Linear(8, 3))
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=gen))
    return net


def _params(model: nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


def _buffers(model: nn.Module) -> list[torch.Tensor]:
    return [b.detach().clone() for b in model.buffers()]


def test_ema_decay_zero_copies_student_and_one_keeps_teacher():
    student, teacher = _net(0), _net(1)
    student(
        torch.randn(16, 4, generator=torch.Generator().manual_seed(2))
    )  # train-mode forward: student BN running stats move away from the teacher's
    teacher_params, teacher_buffers = _params(teacher), _buffers(teacher)

    ema_update(teacher, student, decay=1.0)
    for t, before in zip(teacher.parameters(), teacher_params):
        assert torch.equal(t, before)

    ema_update(teacher, student, decay=0.0)
    for t, s in zip(teacher.parameters(), student.parameters()):
        assert torch.equal(t, s)
    for t, before in zip(teacher.buffers(), teacher_buffers):  # parameters only: buffers untouched
        assert torch.equal(t, before)


def test_ema_intermediate_decay_and_validation():
    student, teacher = _net(0), _net(1)
    expected = [0.99 * t + 0.01 * s for t, s in zip(_params(teacher), _params(student))]
    ema_update(teacher, student, decay=0.99)
    for t, e in zip(teacher.parameters(), expected):
        torch.testing.assert_close(t, e)
    with pytest.raises(ValueError, match="decay"):
        ema_update(teacher, student, decay=1.5)
    with pytest.raises(ValueError, match="different parameters"):
        ema_update(teacher, nn.Linear(4, 3), decay=0.5)


def test_make_teacher_copy_buffers_and_teacher_mode():
    student = _net(0)
    teacher = make_teacher(student)
    assert all(not p.requires_grad for p in teacher.parameters())
    assert all(p.requires_grad for p in student.parameters())
    for t, s in zip(teacher.parameters(), student.parameters()):
        assert torch.equal(t, s) and t.data_ptr() != s.data_ptr()

    student(torch.randn(16, 4, generator=torch.Generator().manual_seed(2)))
    copy_buffers(teacher, student)
    for t, s in zip(teacher.buffers(), student.buffers()):
        assert torch.equal(t, s)

    teacher_mode(teacher, "batch")
    assert teacher[1].training and not teacher[3].training  # BN on batch statistics, dropout off
    teacher_mode(teacher, "copy_student")
    assert not any(m.training for m in teacher.modules())
    with pytest.raises(ValueError, match="bn_mode"):
        teacher_mode(teacher, "ema")


def test_pseudo_labels_below_threshold_get_ignore_id():
    logits = torch.tensor(
        [
            [5.0, 0.0, 0.0],  # p = 0.987 -> kept, class 0
            [0.0, 1.0, 0.0],  # p = 0.576 -> ignored
            [0.0, 0.0, 3.0],  # p = 0.909 -> kept, class 2
            [0.0, 2.9, 0.0],  # p = 0.901 -> kept at 0.9, ignored at 0.95
        ]
    )
    labels, confidence = pseudo_labels(logits, threshold=0.9, ignore_index=19)
    assert labels.tolist() == [0, 19, 2, 1]
    torch.testing.assert_close(confidence, torch.softmax(logits, 1).max(1).values)
    labels, _ = pseudo_labels(logits, threshold=0.95, ignore_index=16)
    assert labels.tolist() == [0, 16, 16, 16]
    assert pseudo_labels(logits, threshold=0.0)[0].tolist() == [0, 1, 2, 1]


def test_scan_views_mirror_then_turn_and_their_mean_softmax():
    scan = torch.tensor([[1.0, 2.0, 3.0, 0.5], [-4.0, 5.0, -6.0, 0.25]])
    views = scan_views(scan, 4)
    mirrors = [
        [[1.0, 2.0], [-4.0, 5.0]],
        [[-1.0, 2.0], [4.0, 5.0]],
        [[1.0, -2.0], [-4.0, -5.0]],
        [[-1.0, -2.0], [4.0, -5.0]],
    ]
    assert [v[:, :2].tolist() for v in views] == mirrors
    assert all(torch.equal(v[:, 2:], scan[:, 2:]) for v in views)  # z and intensity untouched
    assert len(scan_views(scan, 1)) == 1 and torch.equal(scan_views(scan, 1)[0], scan)
    # 8 views: the four mirrors, then the four mirrors turned by 45 degrees (x' = c x - s y, y' = s x + c y)
    eight = scan_views(scan, 8)
    assert [v[:, :2].tolist() for v in eight[:4]] == mirrors
    h = math.sqrt(0.5)
    for view, mirrored in zip(eight[4:], mirrors):
        m = torch.tensor(mirrored)
        torch.testing.assert_close(view[:, :2], torch.stack([h * (m[:, 0] - m[:, 1]), h * (m[:, 0] + m[:, 1])], 1))
        torch.testing.assert_close(view[:, :2].norm(dim=1), m.norm(dim=1))  # a turn keeps the range
        assert torch.equal(view[:, 2:], scan[:, 2:])
    # 12 views: turns by 0, 30 and 60 degrees
    twelve = scan_views(torch.tensor([[1.0, 0.0, 0.0, 0.0]]), 12)
    angles = [math.degrees(math.atan2(float(v[0, 1]), float(v[0, 0]))) for v in twelve[::4]]
    assert angles == pytest.approx([0.0, 30.0, 60.0])
    for bad in (0, 5, 6, 36):
        with pytest.raises(ValueError, match="views"):
            scan_views(scan, bad)
    a = torch.tensor([[4.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    b = torch.tensor([[0.0, 4.0, 0.0], [0.0, 0.0, 2.0]])
    mean = mean_view_probs([a, b])
    torch.testing.assert_close(mean, (torch.softmax(a, 1) + torch.softmax(b, 1)) / 2)


def test_class_balanced_pseudo_labels_keep_a_share_of_every_predicted_class():
    # class 0: confident (0.99, 0.98, 0.97, 0.96 and one 0.5); class 1: never above 0.8 (0.8, 0.7, 0.6, 0.55)
    probs = torch.tensor(
        [
            [0.99, 0.01],
            [0.98, 0.02],
            [0.97, 0.03],
            [0.96, 0.04],
            [0.5, 0.5],
            [0.2, 0.8],
            [0.3, 0.7],
            [0.4, 0.6],
            [0.45, 0.55],
        ]
    )
    logits = probs.log()
    plain, confidence = pseudo_labels(logits, threshold=0.9, ignore_index=19)
    assert plain.tolist() == [0, 0, 0, 0, 19, 19, 19, 19, 19]  # the global threshold: nothing of class 1
    balanced, same_confidence = pseudo_labels(logits, threshold=0.9, ignore_index=19, class_share=0.5)
    torch.testing.assert_close(same_confidence, confidence)
    # class 0 keeps everything above 0.9 (more than half of its 5 points); class 1 keeps its top half (0.8, 0.7)
    assert balanced.tolist() == [0, 0, 0, 0, 19, 1, 1, 19, 19]
    # share 1 keeps every point; the confident class never drops below the global threshold's set
    assert pseudo_labels(logits, 0.9, 19, class_share=1.0)[0].tolist() == [0, 0, 0, 0, 0, 1, 1, 1, 1]
    assert (pseudo_labels(logits, 0.9, 19, class_share=0.01)[0][plain != 19] == 0).all()
    with pytest.raises(ValueError, match="class_share"):
        pseudo_labels(logits, 0.9, 19, class_share=0.0)
    with pytest.raises(InputError, match="pseudo_class_share"):
        load_config(SegTrainConfig, None, ["mode=semi", "semi.pseudo_class_share=1.5"])


def test_consistency_loss_is_mse_of_softmaxes_and_only_trains_student():
    gen = torch.Generator().manual_seed(0)
    student_logits = torch.randn(50, 6, generator=gen, requires_grad=True)
    teacher_logits = torch.randn(50, 6, generator=gen, requires_grad=True)
    loss = consistency_loss(student_logits, teacher_logits)
    expected = ((torch.softmax(student_logits, 1) - torch.softmax(teacher_logits, 1)) ** 2).mean()  # over N x C
    torch.testing.assert_close(loss, expected)
    loss.backward()
    assert student_logits.grad is not None and teacher_logits.grad is None
    assert consistency_loss(teacher_logits, teacher_logits).item() == 0.0
    with pytest.raises(ValueError, match="shape"):
        consistency_loss(torch.zeros(3, 2), torch.zeros(3, 4))


def test_config_defaults_and_total_loss():
    cfg = MeanTeacherConfig()
    assert (cfg.ema_decay, cfg.pseudo_threshold, cfg.consistency_weight) == (0.99, 0.9, 200.0)
    assert cfg.num_areas_choices == (3, 4, 5, 6) and cfg.bn_mode == "batch"
    one = torch.tensor(1.0)
    assert total_loss(one, 2 * one, 0.01 * one, cfg).item() == pytest.approx(1 + 2 + 2)
    assert total_loss(one, 2 * one, None, cfg).item() == pytest.approx(3)


def test_consistency_rampup_is_the_sigmoid_ramp_and_scales_only_the_mt_term():
    assert consistency_rampup(0, 100) == pytest.approx(math.exp(-5.0))
    assert consistency_rampup(50, 100) == pytest.approx(math.exp(-1.25))
    assert consistency_rampup(100, 100) == 1.0 and consistency_rampup(500, 100) == 1.0
    assert consistency_rampup(0, 0) == 1.0  # no ramp-up: constant weight
    ramp = [consistency_rampup(t, 100) for t in range(101)]
    assert all(a < b for a, b in zip(ramp, ramp[1:]))
    cfg = MeanTeacherConfig(consistency_weight=200.0, consistency_rampup_steps=100)
    one = torch.tensor(1.0)
    assert total_loss(one, 2 * one, 0.01 * one, cfg, step=50).item() == pytest.approx(3 + 2 * math.exp(-1.25))
    assert total_loss(one, 2 * one, 0.01 * one, cfg, step=100).item() == pytest.approx(5)
    with pytest.raises(ValueError, match="consistency_rampup_steps"):
        SemiConfig(consistency_rampup_steps=-1)
