"""u4d_aug.runfolder: where a training run starts: step 0, the newest checkpoint, or a refusal."""

from __future__ import annotations

import pytest

from u4d_aug.errors import InputError
from u4d_aug.runfolder import prepare, resume_point


def test_resume_point_of_fresh_unfinished_and_checkpointed_folders(tmp_path):
    out = tmp_path / "run"
    assert resume_point(out, None) is None and resume_point(out, "last") is None  # fresh
    out.mkdir()
    (out / "log.jsonl").write_text('{"step": 1}\n')
    assert resume_point(out, None) is None and resume_point(out, "last") is None  # killed before a checkpoint
    (out / "checkpoints").mkdir()
    for step in (2, 10):
        (out / "checkpoints" / f"step_{step:07d}.pt").write_bytes(b"x")
    assert resume_point(out, "last") == out / "checkpoints" / "step_0000010.pt"
    with pytest.raises(InputError, match="holds a previous run \\(newest checkpoint step_0000010.pt\\); pass --resume"):
        resume_point(out, None)
    assert resume_point(out, out / "checkpoints" / "step_0000002.pt") == out / "checkpoints" / "step_0000002.pt"
    with pytest.raises(InputError, match="nope.pt: checkpoint to resume from not found"):
        resume_point(out, tmp_path / "nope.pt")


def test_prepare_empties_an_unfinished_log_and_removes_temp_files(tmp_path, caplog):
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    (out / "log.jsonl").write_text('{"step": 1}\n')
    (out / "checkpoints" / ".step_0000002.pt.ab12.tmp").write_bytes(b"half")
    with caplog.at_level("INFO", logger="u4d_aug.runfolder"):
        prepare(out, None)
    assert not (out / "log.jsonl").exists() and not list(out.rglob("*.tmp"))
    assert "removed 1 temp file(s)" in caplog.text and "starting it again from step 0" in caplog.text
    (out / "log.jsonl").write_text('{"step": 1}\n')
    prepare(out, out / "checkpoints" / "step_0000001.pt")  # resuming: the trainer rewinds the log itself
    assert (out / "log.jsonl").read_text() == '{"step": 1}\n'
