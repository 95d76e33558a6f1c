"""u4d_aug.io: atomic writes with the umask's mode and one-line errors, .npy without pickles, json without NaN."""

from __future__ import annotations

import json
import math
import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.tiny_nets import REPO
from u4d_aug.errors import InputError
from u4d_aug.io import (
    atomic_open,
    atomic_save_npy,
    atomic_write_json,
    atomic_write_text,
    dumps_json,
    json_safe,
    load_npy,
    make_folder,
    read_json_file,
    remove_temp_files,
)


def test_atomic_writes_honour_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
        atomic_save_npy(tmp_path / "b.npy", np.zeros(3))
        os.umask(0o077)
        atomic_write_text(tmp_path / "c.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "b.npy").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "c.txt").stat().st_mode) == 0o600


def test_a_folder_as_the_file_or_a_file_as_the_folder_is_one_line(tmp_path):
    (tmp_path / "dir").mkdir()
    with pytest.raises(InputError, match="is a folder; expected a file path"):
        atomic_write_text(tmp_path / "dir", "x")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is a file; expected an output folder"):
        atomic_write_text(tmp_path / "file" / "a.txt", "x")
    with pytest.raises(InputError, match="is a file"):
        make_folder(tmp_path / "file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir", "file"]


def _writable(folder: str) -> bool:
    """Whether a file can be made in `folder` (root passes permission bits; a read-only mount stops everyone)."""
    try:
        with open(os.path.join(folder, ".u4d_probe"), "w"):
            pass
    except OSError:
        return False
    os.unlink(os.path.join(folder, ".u4d_probe"))
    return True


@pytest.mark.skipif(_writable("/sys"), reason="/sys is writable here")
def test_an_unwritable_place_is_one_line():
    with pytest.raises(InputError, match="/sys/u4d_test: cannot create the output folder"):
        atomic_write_text("/sys/u4d_test/a.txt", "x")
    with pytest.raises(InputError, match="cannot write here|not writable"):
        atomic_write_text("/sys/a.txt", "x")


def test_a_full_disk_is_one_line_and_leaves_no_temp_file(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(InputError, match=r"a\.txt: cannot write \(No space left on device\)"):
        atomic_write_text(tmp_path / "a.txt", "x")
    assert list(tmp_path.iterdir()) == []


def test_a_write_interrupted_midway_keeps_the_old_file_and_leaves_no_temp_file(tmp_path, monkeypatch):
    target = tmp_path / "a.json"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="midway"), atomic_open(target) as f:  # the writer fails after some bytes
        f.write(b'{"half": ')
        raise RuntimeError("midway")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]

    def full_disk(array_file, array):  # np.save runs out of space halfway through the array
        array_file.write(b"\x93NUMPY half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "save", full_disk)
    (tmp_path / "b.npy").write_bytes(b"old array")
    with pytest.raises(InputError, match="No space left on device"):
        atomic_save_npy(tmp_path / "b.npy", np.zeros(1000))
    assert (tmp_path / "b.npy").read_bytes() == b"old array"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.npy"]


def test_a_write_interrupted_at_the_rename_keeps_the_old_file_and_leaves_no_temp_file(tmp_path, monkeypatch):
    target = tmp_path / "a.txt"
    target.write_text("old")

    def interrupted(src, dst):  # Ctrl-C between the written temp file and the rename
        assert Path(src).read_text() == "new" and Path(src).parent == tmp_path
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_text(target, "new")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_a_writer_killed_midway_leaves_the_old_file_whole(tmp_path):
    """SIGKILL runs no clean-up: the old file stays whole beside a half temp file, which `remove_temp_files` finds."""
    target = tmp_path / "model.pt"
    target.write_bytes(b"old weights")
    code = (
        "import sys, time; from u4d_aug.io import atomic_open\n"
        "with atomic_open(sys.argv[1]) as f:\n"
        "    f.write(b'x' * 1_000_000); f.flush(); print('written', flush=True); time.sleep(60)\n"
    )
    writer = subprocess.Popen([sys.executable, "-c", code, str(target)], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout.readline().strip() == "written"
    finally:
        writer.kill()
        writer.wait(timeout=30)
    assert writer.returncode == -signal.SIGKILL
    assert target.read_bytes() == b"old weights"
    (temp,) = [p for p in tmp_path.iterdir() if p != target]
    assert temp.name.startswith(".model.pt.") and temp.name.endswith(".tmp") and temp.stat().st_size == 1_000_000
    assert remove_temp_files(tmp_path) == 1 and list(tmp_path.iterdir()) == [target]


def test_temp_files_of_killed_writes_are_removed_and_nothing_else(tmp_path):
    (tmp_path / "sub").mkdir()
    for name in (".a.bin.x1.tmp", "sub/.step_0000002.pt.k9.tmp", ".frd.pt.q.tmp"):
        (tmp_path / name).write_bytes(b"half")
    for name in ("keep.tmp", ".keep.tmp", "a.bin"):
        (tmp_path / name).write_bytes(b"whole")
    assert remove_temp_files(tmp_path, "frd") == 1
    assert remove_temp_files(tmp_path) == 2
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == [".keep.tmp", "a.bin", "keep.tmp"]
    assert remove_temp_files(tmp_path / "missing") == 0


def test_load_npy_refuses_objects_and_truncated_files(tmp_path):
    np.save(tmp_path / "ok.npy", np.eye(2, dtype=np.float16))
    np.testing.assert_array_equal(load_npy(tmp_path / "ok.npy", "array"), np.eye(2))
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="refused as an array: it holds python objects"):
        load_npy(tmp_path / "objects.npy", "array")
    whole = (tmp_path / "ok.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(whole[:-3])
    (tmp_path / "empty.npy").write_bytes(b"")
    (tmp_path / "text.npy").write_text("hello")
    for name in ("cut", "empty", "text"):
        with pytest.raises(InputError, match=f"{name}.npy: not a readable array"):
            load_npy(tmp_path / f"{name}.npy", "array")
    with pytest.raises(InputError, match="not found"):
        load_npy(tmp_path / "missing.npy", "array")


def test_json_has_null_where_a_number_is_not_finite(tmp_path):
    value = {"a": float("nan"), "b": [np.float32(np.inf), 1.5, np.int64(2)], "c": np.array([np.nan, 2.0]), "d": None}
    assert json_safe(value) == {"a": None, "b": [None, 1.5, 2], "c": [None, 2.0], "d": None}
    text = dumps_json(value)
    assert "NaN" not in text and "Infinity" not in text and json.loads(text)["b"][2] == 2
    atomic_write_json(tmp_path / "x.json", {"miou": math.nan, "path": Path("p")})
    assert json.loads((tmp_path / "x.json").read_text()) == {"miou": None, "path": "p"}


def test_read_json_file_names_the_file_and_what_went_wrong(tmp_path):
    good = tmp_path / "good.json"
    good.write_text('{"a": [1, 2]}')
    assert read_json_file(good, "x") == {"a": [1, 2]}
    (tmp_path / "bad.json").write_text('{"a": [1,')
    (tmp_path / "latin.json").write_bytes(b'{"a": "\xe9"}')
    cases = [
        ("missing.json", "missing.json: not found (expected the results.json of `u4d experiment`)"),
        ("bad.json", "bad.json: not valid json (Expecting value, line 1)"),
        ("latin.json", "latin.json: cannot read ("),
    ]
    for name, message in cases:
        with pytest.raises(InputError) as err:
            read_json_file(tmp_path / name, "the results.json of `u4d experiment`")
        assert message in str(err.value) and "\n" not in str(err.value), name
