"""Where a training run in an output folder starts: step 0, or the checkpoint it resumes from.

A folder with checkpoints holds a previous run: it continues only with --resume. A folder with a config and a log
but no checkpoint holds a run killed before its first checkpoint: it is started again from step 0 (its log
emptied), with or without --resume, with a one-line notice. Temp files of killed atomic writes are removed first.
Call under the folder's run lock (`u4d_aug.runlock`), so that no other run is writing there.
"""

from __future__ import annotations

import logging
from pathlib import Path

from u4d_aug.errors import InputError
from u4d_aug.io import remove_temp_files

logger = logging.getLogger(__name__)

CHECKPOINT_GLOB = "step_*.pt"


def checkpoints(out_dir: Path) -> list[Path]:
    """OUT/checkpoints/step_*.pt, oldest first (zero-padded step numbers sort by name)."""
    return sorted((Path(out_dir) / "checkpoints").glob(CHECKPOINT_GLOB))


def resume_point(out_dir: Path, resume: str | Path | None) -> Path | None:
    """The checkpoint a run in `out_dir` resumes from, or None to start at step 0 (no side effects).

    resume None: step 0, refused when the folder has checkpoints; "last": the newest checkpoint, or step 0 when
    there is none yet; a path: that file.
    """
    out_dir = Path(out_dir)
    found = checkpoints(out_dir)
    if resume is None:
        if found:
            raise InputError(
                f"{out_dir}: holds a previous run (newest checkpoint {found[-1].name}); pass --resume to continue it "
                "or choose another --out"
            )
        return None
    if str(resume) == "last":
        return found[-1] if found else None
    path = Path(resume)
    if not path.is_file():
        raise InputError(f"{path}: checkpoint to resume from not found")
    return path


def prepare(out_dir: Path, start: Path | None, log_name: str = "log.jsonl") -> None:
    """Remove temp files of killed writes; starting at step 0 in an unfinished run's folder, empty its log (notice)."""
    out_dir = Path(out_dir)
    removed = remove_temp_files(out_dir)
    if removed:
        logger.info("%s: removed %d temp file(s) of a killed run", out_dir, removed)
    log_path = out_dir / log_name
    if start is None and log_path.is_file():
        logger.info("%s: run killed before its first checkpoint; starting it again from step 0", out_dir)
        log_path.unlink()
