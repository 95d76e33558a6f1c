"""A killed `u4d train-extractor` run continues from its last snapshot to the same weights (same hash) as an
uninterrupted run, its log reads as one run's, and a snapshot of another config is refused with one line."""

from __future__ import annotations

import pytest
import torch

from tests.tiny_nets import EXTRACTOR_TINY as TINY_CONFIG
from tests.tiny_worlds import write_tiny_root
from u4d_aug.config import load_config
from u4d_aug.errors import InputError
from u4d_aug.io import read_jsonl
from u4d_aug.metrics import extractors
from u4d_aug.metrics.extractors import ExtractorConfig, load_extractor, train_extractor

STEPS = ["train.steps=6", "train.checkpoint_every=2", "train.log_every=1", "train.val_scans=0"]


def config(root, out, *extra: str) -> ExtractorConfig:
    return load_config(ExtractorConfig, TINY_CONFIG, [f"data.root={root}", f"out_dir={out}", *STEPS, *extra])


@pytest.mark.parametrize("kind", ["frd", "fpd"])
def test_killed_run_resumes_to_the_same_weights(kind, tmp_path, monkeypatch):
    torch.set_num_threads(1)
    root = write_tiny_root(tmp_path / "root")
    _, whole = train_extractor(kind, config(root, tmp_path / "whole"))

    real_check = extractors.check_finite_loss

    def killed_at_step_5(loss, step, *args):
        if step == 5:
            raise KeyboardInterrupt  # stands for a kill between the step-4 snapshot and the end
        real_check(loss, step, *args)

    monkeypatch.setattr(extractors, "check_finite_loss", killed_at_step_5)
    out = tmp_path / "killed"
    with pytest.raises(KeyboardInterrupt):
        train_extractor(kind, config(root, out))
    assert (out / f"{kind}_partial.pt").is_file() and not (out / f"{kind}.pt").exists()
    assert [r["step"] for r in read_jsonl(out / f"{kind}_log.jsonl")] == [1, 2, 3, 4]
    monkeypatch.setattr(extractors, "check_finite_loss", real_check)

    path, resumed = train_extractor(kind, config(root, out))
    assert resumed == whole  # weights hash: bit-identical to the uninterrupted run
    a, b = load_extractor(path).model.state_dict(), load_extractor(tmp_path / "whole" / f"{kind}.pt").model.state_dict()
    assert all(torch.equal(a[name], b[name]) for name in a)
    assert [r["step"] for r in read_jsonl(out / f"{kind}_log.jsonl")] == [1, 2, 3, 4, 5, 6]
    assert not (out / f"{kind}_partial.pt").exists()  # finished runs leave no snapshot


def test_snapshot_of_another_config_is_refused(tmp_path, monkeypatch):
    torch.set_num_threads(1)
    root = write_tiny_root(tmp_path / "root")

    def killed_at_step_3(loss, step, *args):
        if step == 3:
            raise KeyboardInterrupt

    monkeypatch.setattr(extractors, "check_finite_loss", killed_at_step_3)
    with pytest.raises(KeyboardInterrupt):
        train_extractor("frd", config(root, tmp_path / "out"))
    monkeypatch.undo()
    with pytest.raises(InputError, match="frd_partial.pt: an unfinished frd run with another config"):
        train_extractor("frd", config(root, tmp_path / "out", "train.lr=0.01"))
