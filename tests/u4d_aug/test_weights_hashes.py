"""The shipped weights are the tensors their hashes name: each weights/*.pt file's `weights_hash` recomputed from its
tensors and config (`weights.weights_digest`) equals the stored field, and its `hash` the weights/README.md row."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from u4d_aug.weights import EXTRACTOR_KINDS, SHIPPED_DIR, weights_digest

SHIPPED = sorted(SHIPPED_DIR.glob("*.pt"))


def readme_hashes() -> dict[str, str]:
    """{file name: hash} of the weights/README.md table (the hash column is the second to last)."""
    rows = {}
    for line in (SHIPPED_DIR / "README.md").read_text().splitlines():
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if line.startswith("| `") and cells[0].endswith(".pt`"):
            rows[cells[0].strip("`")] = cells[-2].strip("`")
    return rows


def test_every_shipped_file_has_a_readme_row():
    assert SHIPPED and set(readme_hashes()) == {path.name for path in SHIPPED}


@pytest.mark.parametrize("path", SHIPPED, ids=lambda path: path.name)
def test_the_hashes_of_a_shipped_file_are_those_of_its_tensors(path: Path):
    state = torch.load(path, weights_only=True)
    digest = weights_digest(state["model"], state["config"])  # as export_weights wrote it, from the stored tensors
    assert digest == state["weights_hash"], f"{path.name}: its tensors hash to {digest}, not to its weights_hash"
    if state["kind"] not in EXTRACTOR_KINDS:  # an extractor keeps its training checkpoint's hash (FRD/FPD names)
        assert state["hash"] == digest, path.name
    assert readme_hashes()[path.name] == state["hash"], path.name


def test_the_recomputed_hash_sees_one_zeroed_tensor():
    state = torch.load(SHIPPED_DIR / "u4d.pt", weights_only=True)
    name = next(name for name, tensor in sorted(state["model"].items()) if bool(tensor.float().abs().sum() > 0))
    zeroed = {**state["model"], name: torch.zeros_like(state["model"][name])}
    assert weights_digest(zeroed, state["config"]) != state["weights_hash"]
