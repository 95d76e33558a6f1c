"""Output-folder ownership: simulate, generate and bank-real write only into an empty --out or their own output."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from tests.tiny_nets import REPO, gen_config
from tests.tiny_worlds import write_toy_root
from u4d_aug.config import load_config
from u4d_aug.data.sim.config import SimConfig
from u4d_aug.data.sim.writer import simulate
from u4d_aug.errors import InputError
from u4d_aug.generate import generate_bank
from u4d_aug.outfolder import check_output_folder, folder_content, missing_folders, removed_if_failed
from u4d_aug.real_bank import write_real_bank

SIM_TINY = REPO / "configs" / "sim" / "tiny.yaml"


def tree_digest(root: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under root."""
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    """A SemanticKITTI root without a manifest (as a real dataset is), with poses and calib beside sequence 00."""
    root = write_toy_root(tmp_path / "dataset", ("00",), frames=2)
    (root / "sequences" / "00" / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    (root / "sequences" / "00" / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return root


def test_the_lock_and_temp_files_are_not_content(tmp_path: Path):
    (tmp_path / ".lock").write_text("{}")
    (tmp_path / ".scan.bin.abc123.tmp").write_bytes(b"")
    assert folder_content(tmp_path) == [] and folder_content(tmp_path / "missing") == []
    check_output_folder(tmp_path, "a simulated world", lambda record: False)
    (tmp_path / ".hidden").write_text("")  # a dotfile that is no temp file is content
    with pytest.raises(InputError, match=r"holds \.hidden and no manifest.json of a simulated world"):
        check_output_folder(tmp_path, "a simulated world", lambda record: False)


def test_simulate_into_a_dataset_root_is_refused_and_writes_nothing(dataset: Path):
    before = tree_digest(dataset)
    cfg = load_config(SimConfig, SIM_TINY, [])
    with pytest.raises(InputError, match=r"dataset: holds sequences \(a dataset root\?\) and no manifest.json"):
        simulate(dataset, sequences=1, frames=2, seed=0, config=cfg, progress=False)
    assert tree_digest(dataset) == before  # poses, calib and scans untouched, no frame added
    assert not (dataset / "manifest.json").exists()


def test_simulate_resumes_its_own_world_but_not_a_bank(tmp_path: Path):
    cfg = load_config(SimConfig, SIM_TINY, [])
    for _ in range(2):  # the second run finds its own world: it resumes
        simulate(tmp_path / "world", sequences=1, frames=2, seed=0, config=cfg, progress=False)
    real = write_real_bank(tmp_path / "world", ["00"], tmp_path / "bank", None)
    assert len(real["samples"]) == 2
    before = tree_digest(tmp_path / "bank")
    with pytest.raises(InputError, match=r"bank/manifest.json: not the manifest of a simulated world"):
        simulate(tmp_path / "bank", sequences=1, frames=1, seed=0, config=cfg, progress=False)
    assert tree_digest(tmp_path / "bank") == before


def test_generate_into_a_dataset_root_is_refused_before_any_sample(dataset: Path, untrained_checkpoints):
    before = tree_digest(dataset)
    with pytest.raises(InputError, match=r"no manifest.json of a generated bank"):
        generate_bank(gen_config(untrained_checkpoints, "num=1", "mode=baseline"), dataset, progress=False)
    assert tree_digest(dataset) == before


def test_bank_real_refuses_a_generated_bank_and_a_dataset(dataset: Path, tmp_path: Path, untrained_checkpoints):
    bank = tmp_path / "generated"
    generate_bank(gen_config(untrained_checkpoints, "num=1", "mode=baseline"), bank, progress=False)
    for folder, message in ((bank, "not the manifest of a bank of real scans"), (dataset, "a dataset root")):
        before = tree_digest(folder)
        with pytest.raises(InputError, match=message):
            write_real_bank(dataset, ["00"], folder, None)
        assert tree_digest(folder) == before
    # a copy of the bank is still its own kind to generate: it resumes
    shutil.copytree(bank, tmp_path / "copy")
    generate_bank(gen_config(untrained_checkpoints, "num=1", "mode=baseline"), tmp_path / "copy", progress=False)


def test_a_failed_run_leaves_no_folder_it_created(tmp_path: Path):
    out = tmp_path / "runs" / "a"
    assert missing_folders(out) == [out, tmp_path / "runs"]
    with pytest.raises(RuntimeError), removed_if_failed(out, ("config.yaml",)):
        out.mkdir(parents=True)
        (out / "config.yaml").write_text("steps: 1\n")  # its scaffolding: removed with it
        raise RuntimeError("bad data")
    assert not (tmp_path / "runs").exists()
    with removed_if_failed(out):  # a run that succeeds keeps its folder
        out.mkdir(parents=True)
    assert out.is_dir() and missing_folders(out) == []


def test_a_failed_run_keeps_a_folder_that_was_there_or_holds_more(tmp_path: Path):
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(RuntimeError), removed_if_failed(existing):
        raise RuntimeError("bad data")
    assert existing.is_dir()
    for other in ("log.jsonl", ".lock"):  # a file the run wrote, another run's lock
        out = tmp_path / f"new{other}"
        with pytest.raises(RuntimeError), removed_if_failed(out, ("config.yaml",)):
            out.mkdir()
            (out / "config.yaml").write_text("steps: 1\n")
            (out / other).write_text("{}\n")
            raise RuntimeError("failed later")
        assert sorted(p.name for p in out.iterdir()) == sorted(["config.yaml", other])
