"""A bank of generated scans in SemanticKITTI layout, written atomically and resumably (issue 6 §8).

BANK/sequences/00/velodyne/NNNNNN.bin   (N, 4) float32 points (read back with `read_kitti_scan`)
BANK/sequences/00/mask/NNNNNN.npy       (H, W) bool: the stage-1 mask m_u (predicted, or real in completion mode)
BANK/sequences/00/uncertainty/NNNNNN.npy (H, W) float16 entropy image, where the source had probabilities
BANK/sequences/00/stage1/NNNNNN.npy     (2, H, W) float16 x0_u in [-1, 1]: stage 1's output (u4d) or the real P_u
                                        that stage 2 completed (complete mode)
BANK/sequences/00/empty/NNNNNN         marker of a sample with no return at all (it gets no .bin: SemanticKITTI
                                        readers reject empty scans, and consumers should not see one)
BANK/manifest.json                      config, per-sample seeds, checkpoint sha256[:16], empty samples, completion
The .npy side files are written before the .bin (or marker), so its presence means the sample is complete.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from u4d_aug.data.formats import write_kitti_scan
from u4d_aug.errors import InputError
from u4d_aug.io import atomic_save_npy, atomic_write_bytes, atomic_write_json

BANK_SEQUENCE = "00"
MANIFEST = "manifest.json"


@dataclass(frozen=True)
class BankLayout:
    """Paths of sample i of a bank rooted at `root`."""

    root: Path

    @property
    def sequence_dir(self) -> Path:
        return Path(self.root) / "sequences" / BANK_SEQUENCE

    @property
    def manifest_path(self) -> Path:
        return Path(self.root) / MANIFEST

    def scan_path(self, index: int) -> Path:
        return self.sequence_dir / "velodyne" / f"{index:06d}.bin"

    def mask_path(self, index: int) -> Path:
        return self.sequence_dir / "mask" / f"{index:06d}.npy"

    def uncertainty_path(self, index: int) -> Path:
        return self.sequence_dir / "uncertainty" / f"{index:06d}.npy"

    def empty_path(self, index: int) -> Path:
        return self.sequence_dir / "empty" / f"{index:06d}"

    def stage1_path(self, index: int) -> Path:
        return self.sequence_dir / "stage1" / f"{index:06d}.npy"

    def is_empty(self, index: int) -> bool:
        return self.empty_path(index).is_file()

    def is_done(self, index: int) -> bool:
        """The .bin (or the empty marker) is written last: its presence means every file of the sample is there."""
        return self.scan_path(index).is_file() or self.is_empty(index)


def file_sha256(path: str | Path, length: int = 16) -> str:
    """Hex sha256 of a file's bytes, first `length` characters (checkpoint identity in the manifest)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:length]


def write_sample(
    layout: BankLayout,
    index: int,
    points: np.ndarray,
    mask: np.ndarray | None = None,
    uncertainty: np.ndarray | None = None,
    x0_u: np.ndarray | None = None,
) -> None:
    """Write sample `index`: side files first, the scan last (an empty scan as a marker instead of a .bin)."""
    if mask is not None:
        atomic_save_npy(layout.mask_path(index), np.asarray(mask, dtype=bool))
    if uncertainty is not None:
        atomic_save_npy(layout.uncertainty_path(index), np.asarray(uncertainty, dtype=np.float16))
    if x0_u is not None:
        atomic_save_npy(layout.stage1_path(index), np.asarray(x0_u, dtype=np.float16))
    if len(points) == 0:
        atomic_write_bytes(layout.empty_path(index), b"0 points\n")
    else:
        write_kitti_scan(layout.scan_path(index), np.asarray(points, dtype=np.float32))


def read_manifest(root: str | Path) -> dict[str, Any] | None:
    """The bank's manifest, or None if it has none yet."""
    path = BankLayout(Path(root)).manifest_path
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid json ({exc.msg})") from None


def check_compatible(root: str | Path, identity: dict[str, Any]) -> None:
    """Refuse to add samples to a bank written with another config or other checkpoints."""
    old = read_manifest(root)
    if old is None:
        return
    for key, value in identity.items():
        if old.get(key) != value:
            raise InputError(
                f"{BankLayout(Path(root)).manifest_path}: bank was generated with a different {key}; "
                "choose another --out or delete the bank"
            )


def write_manifest(root: str | Path, manifest: dict[str, Any]) -> None:
    """Write BANK/manifest.json atomically."""
    atomic_write_json(BankLayout(Path(root)).manifest_path, manifest)
