"""u4d_aug.runlock: one run per output folder, tested with real processes; stale locks are taken over."""

from __future__ import annotations

import json
import multiprocessing
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from u4d_aug.errors import InputError
from u4d_aug.runlock import LOCK_NAME, is_stale, read_holder, run_lock


def hold(folder: str, ready, done) -> None:
    """Child process: hold the folder's lock until told to let go."""
    with run_lock(folder):
        ready.set()
        done.wait(60)


def try_lock(folder: str, results) -> None:
    """Child process: try to lock the folder; report the outcome."""
    try:
        with run_lock(folder):
            results.put("locked")
    except InputError as error:
        results.put(f"refused: {error}")


@pytest.fixture
def spawn():
    return multiprocessing.get_context("spawn")


def test_a_second_process_is_refused_while_the_first_holds_the_folder(tmp_path, spawn):
    folder = str(tmp_path / "out")
    ready, done, results = spawn.Event(), spawn.Event(), spawn.Queue()
    first = spawn.Process(target=hold, args=(folder, ready, done))
    first.start()
    try:
        assert ready.wait(60)
        holder = read_holder(Path(folder) / LOCK_NAME)
        assert holder["pid"] == first.pid and holder["host"] == socket.gethostname()
        second = spawn.Process(target=try_lock, args=(folder, results))
        second.start()
        second.join(60)
        message = results.get(timeout=10)
        assert message.startswith(f"refused: {folder}: in use by another run (pid {first.pid} on host ")
        assert "\n" not in message
        with pytest.raises(InputError, match="in use by another run"), run_lock(folder):  # this process too
            pass
    finally:
        done.set()
        first.join(60)
    assert not (Path(folder) / LOCK_NAME).exists()  # released when the holder ended its run
    third = spawn.Process(target=try_lock, args=(folder, results))
    third.start()
    third.join(60)
    assert results.get(timeout=10) == "locked"


def test_the_lock_of_a_killed_process_is_taken_over_with_a_warning(tmp_path, caplog):
    folder = tmp_path / "out"
    code = f"import os\nfrom u4d_aug.runlock import run_lock\nwith run_lock({str(folder)!r}): os._exit(0)"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)  # dies holding it, as a SIGKILL would
    left = read_holder(folder / LOCK_NAME)
    assert left["pid"] > 0 and is_stale(left)
    with caplog.at_level("WARNING", logger="u4d_aug.runlock"), run_lock(folder) as path:
        assert read_holder(path)["pid"] == os.getpid()
    assert f"took over the lock of a run that is gone (pid {left['pid']} on host" in caplog.text
    assert not path.exists()


def test_unreadable_recycled_and_foreign_locks(tmp_path):
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / LOCK_NAME).write_text("")  # a run killed while writing its lock
    with run_lock(folder):
        pass
    (folder / LOCK_NAME).write_bytes(b"\xff\xfe\x00garbage")  # bytes that are no text: as unreadable
    with run_lock(folder):
        pass
    mine = {"pid": os.getpid(), "host": socket.gethostname(), "start": "1", "started": 0}
    assert is_stale(mine)  # this pid, but a process started at another time: recycled
    foreign = {"pid": 1, "host": "another-machine", "start": None}
    assert not is_stale(foreign)  # cannot be checked from here
    (folder / LOCK_NAME).write_text(json.dumps(foreign))
    with pytest.raises(InputError, match="pid 1 on host another-machine"), run_lock(folder):
        pass


def test_reentrant_in_one_process_released_on_errors_and_optional(tmp_path):
    folder = tmp_path / "out"
    with pytest.raises(RuntimeError), run_lock(folder):
        with run_lock(folder):  # the experiment runner locks a run folder that train locks again
            assert (folder / LOCK_NAME).is_file()
        assert (folder / LOCK_NAME).is_file()  # the outer holder still has it
        raise RuntimeError("a failing run")
    assert not (folder / LOCK_NAME).exists()
    with run_lock(folder, enabled=False) as path:  # torchrun ranks > 0
        assert path is None and not (folder / LOCK_NAME).exists()
    with run_lock(folder, name=".frd.lock"), run_lock(folder, name=".fpd.lock"):
        assert {p.name for p in folder.iterdir()} == {".frd.lock", ".fpd.lock"}


def test_a_file_in_place_of_the_folder_is_one_line(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is a file; expected an output folder"), run_lock(tmp_path / "file"):
        pass


def test_links_that_leave_the_folder_are_refused_links_inside_it_are_not(tmp_path):
    outside = tmp_path / "outside"
    (outside / "checkpoints").mkdir(parents=True)
    (outside / "log.jsonl").write_text("kept\n")
    out = tmp_path / "out"
    (out / "inner").mkdir(parents=True)
    (out / "alias").symlink_to(out / "inner", target_is_directory=True)  # stays inside: fine
    with run_lock(out):
        pass
    (out / "inner" / "log.jsonl").symlink_to(outside / "log.jsonl")  # a nested file link that leaves
    leaving = r"inner/log.jsonl: a symbolic link to .*outside.*outside the output folder"
    with pytest.raises(InputError, match=leaving), run_lock(out):
        pass
    (out / "inner" / "log.jsonl").unlink()
    (out / "checkpoints").symlink_to(outside / "checkpoints", target_is_directory=True)
    with pytest.raises(InputError, match="checkpoints: a symbolic link"), run_lock(out):
        pass
    assert not (out / LOCK_NAME).exists() and (outside / "log.jsonl").read_text() == "kept\n"


def test_a_failed_run_removes_the_folder_its_lock_created(tmp_path):
    out = tmp_path / "runs" / "a"
    with pytest.raises(InputError, match="bad data"), run_lock(out, scaffolding=("config.yaml",)):
        (out / "config.yaml").write_text("steps: 1\n")
        raise InputError("bad data")
    assert not (tmp_path / "runs").exists()  # the parent it created too
    out.mkdir(parents=True)
    with pytest.raises(InputError, match="bad data"), run_lock(out):
        raise InputError("bad data")
    assert out.is_dir()  # there before the run: kept
