"""One run per output folder: OUT/.lock holds the pid and host of the run writing there.

The lock file is created with O_CREAT | O_EXCL, so of two runs started on one folder exactly one gets it; the
other is refused with one line naming the folder and the holder. A lock whose process is gone (same host, pid not
alive or alive since another start) is stale: it is taken over with a one-line warning, under an flock of the
folder so that two runs cannot both take it over. The lock is removed when the run ends, also on an exception; a
killed run leaves it behind for the next run to take over. Locks are re-entrant within one process (`u4d
experiment` holds a run folder's lock around `segmentation.train.train`, which takes it again). A run that fails
removes the folder its lock created when nothing but its scaffolding was written there (`outfolder.removed_if_failed`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

from u4d_aug.errors import InputError
from u4d_aug.io import current_umask, make_folder
from u4d_aug.outfolder import LOCK_NAME, removed_if_failed

logger = logging.getLogger(__name__)

_HELD: dict[Path, int] = {}  # lock file -> how many nested run_lock calls of this process hold it


def holder_text(holder: dict) -> str:
    """'pid 123 on host h (since 2024-01-01 12:00:00)' of a lock's content."""
    since = holder.get("started")
    when = f" (since {time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(since))})" if since else ""
    return f"pid {holder.get('pid', '?')} on host {holder.get('host', '?')}{when}"


def process_start(pid: int) -> str | None:
    """Start time of process `pid` in clock ticks since boot (/proc/PID/stat field 22), None where unknown."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            stat = f.read()
    except OSError:
        return None
    fields = stat.rpartition(")")[2].split()  # after the command name, which may hold spaces
    return fields[19] if len(fields) > 19 else None


def this_process() -> dict:
    """What a lock file holds: pid, host, process start (ticks since boot) and wall-clock start."""
    pid = os.getpid()
    return {"pid": pid, "host": socket.gethostname(), "start": process_start(pid), "started": time.time()}


def is_stale(holder: dict) -> bool:
    """Whether a lock's run is gone: on this host, its pid is not alive, or now names a process started later."""
    if holder.get("host") != socket.gethostname():
        return False  # another machine's run: it cannot be checked from here
    pid = holder.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        pass  # alive, another user's
    start = process_start(pid)
    return holder.get("start") is not None and start is not None and start != holder["start"]


def read_holder(path: Path) -> dict | None:
    """The content of a lock file; {} when it is unreadable (a run killed while writing it); None when gone."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError):  # undecodable bytes: as unreadable
        return {}
    with contextlib.suppress(json.JSONDecodeError):
        holder = json.loads(text)
        if isinstance(holder, dict):
            return holder
    return {}


def _create(path: Path, holder: dict) -> bool:
    """Create the lock file holding `holder` if none exists (atomic); False when another run has it."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 & ~current_umask())
    except FileExistsError:
        return False
    except OSError as exc:
        raise InputError(
            f"{path.parent}: cannot lock the output folder ({exc.strerror or type(exc).__name__})"
        ) from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(json.dumps(holder) + "\n")
    except OSError as exc:  # a full disk: no empty lock left behind, one line naming it
        path.unlink(missing_ok=True)
        raise InputError(f"{path}: cannot write the run lock ({exc.strerror or type(exc).__name__})") from None
    return True


def _take_over(path: Path, seen: dict, holder: dict) -> bool:
    """Replace the stale lock `seen` by ours, unless another run changed the lock meanwhile (folder flock)."""
    folder_fd = os.open(path.parent, os.O_RDONLY)
    try:
        fcntl.flock(folder_fd, fcntl.LOCK_EX)
        if read_holder(path) != seen:
            return False
        path.unlink(missing_ok=True)
        return _create(path, holder)
    finally:
        os.close(folder_fd)  # releases the flock


def check_links_inside(folder: Path) -> None:
    """InputError naming the first symbolic link under `folder` that leads outside it (a run appends and writes
    through links: a linked log or checkpoints/ folder would put its files elsewhere); links inside it are fine."""
    root = folder.resolve()
    for parent, dirs, files in os.walk(folder):  # does not descend into linked folders
        for name in sorted(dirs + files):
            link = Path(parent) / name
            if not link.is_symlink():
                continue
            target = link.resolve()
            if target != root and root not in target.parents:
                raise InputError(
                    f"{link}: a symbolic link to {target}, outside the output folder {folder}; remove it or choose "
                    "another output folder (nothing is written through a link that leaves it)"
                )


def acquire(folder: str | os.PathLike, name: str = LOCK_NAME) -> Path:
    """Create FOLDER/name for this process (creating the folder); InputError when a live run holds it or a link
    inside it leads out of it."""
    folder = make_folder(folder)
    check_links_inside(folder)
    path = folder / name
    holder = this_process()
    for _ in range(3):  # the lock can vanish or change between our looks at it: look again
        if _create(path, holder):
            return path
        seen = read_holder(path)
        if seen == {}:  # empty: perhaps a run between creating and writing it; look once more after a moment
            time.sleep(0.5)
            seen = read_holder(path)
        if seen is None:
            continue
        if seen and not is_stale(seen):
            raise InputError(
                f"{folder}: in use by another run ({holder_text(seen)}); wait for it or choose another output "
                f"folder (delete {path} if that run is gone)"
            )
        if _take_over(path, seen, holder):
            what = holder_text(seen) if seen else "an unreadable lock"
            logger.warning("%s: took over the lock of a run that is gone (%s)", folder, what)
            return path
    raise InputError(f"{folder}: could not lock the output folder; another run keeps changing {path}")


def release(path: Path) -> None:
    """Remove the lock file if it is still ours (a run that took over a lock we lost keeps its own)."""
    holder = read_holder(path)
    if holder and holder.get("pid") == os.getpid() and holder.get("host") == socket.gethostname():
        path.unlink(missing_ok=True)


@contextlib.contextmanager
def run_lock(
    folder: str | os.PathLike, name: str = LOCK_NAME, enabled: bool = True, scaffolding: tuple[str, ...] = ()
) -> Iterator[Path | None]:
    """Hold FOLDER/name for the body (re-entrant in one process); enabled=False (torchrun ranks > 0) holds nothing.

    A body that raises removes FOLDER when this call created it and it holds nothing but `scaffolding` files (the
    run's config; `outfolder.removed_if_failed`): a failed run leaves no empty output folder behind.
    """
    if not enabled:
        yield None
        return
    key = (Path(folder) / name).resolve()
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield key
        finally:
            _HELD[key] -= 1
        return
    with removed_if_failed(folder, scaffolding):  # after the lock's release
        path = acquire(folder, name)
        _HELD[key] = 1
        try:
            yield path
        finally:
            del _HELD[key]
            release(path)
