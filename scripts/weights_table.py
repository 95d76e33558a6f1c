"""Write u4d_aug/shipped_weights.json from the checkout's weights/*.pt: the table `u4d weights install` checks against.

Run after every re-ship of weights/ (tests/u4d_aug/test_weights_store.py fails until the table matches the files):
    python scripts/weights_table.py
"""

from __future__ import annotations

import torch

from u4d_aug.io import atomic_write_json, file_sha256
from u4d_aug.weights_store import CHECKOUT_DIR, TABLE_FORMAT, TABLE_PATH


def table() -> dict:
    """{format, files: {name: {sha256, bytes, hash}}} of every weights/*.pt."""
    files = {}
    for path in sorted(CHECKOUT_DIR.glob("*.pt")):
        state = torch.load(path, map_location="cpu", weights_only=True)
        files[path.name] = {"sha256": file_sha256(path, 64), "bytes": path.stat().st_size, "hash": state.get("hash")}
    return {"format": TABLE_FORMAT, "files": files}


if __name__ == "__main__":
    record = table()
    atomic_write_json(TABLE_PATH, record)
    print(f"{TABLE_PATH}: {len(record['files'])} files")
