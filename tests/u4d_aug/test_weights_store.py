"""Where the shipped nets are found: explicit folder, checkout, user cache (u4d_aug/weights_store.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from u4d_aug.cli import main
from u4d_aug.errors import InputError
from u4d_aug.io import file_sha256
from u4d_aug.weights_store import (
    CHECKOUT_DIR,
    WEIGHTS_ENV,
    resolve_weights,
    search_dirs,
    shipped_name,
    shipped_table,
    split_weights_dir,
)


def test_the_table_is_the_checkouts_weights_byte_for_byte():
    table = shipped_table()
    files = sorted(CHECKOUT_DIR.glob("*.pt"))
    assert files, "the checkout ships its nets under weights/"
    assert sorted(table) == [path.name for path in files], "run `python scripts/weights_table.py` after a re-ship"
    for path in files:
        entry = table[path.name]
        assert entry["bytes"] == path.stat().st_size and entry["sha256"] == file_sha256(path, 64), path.name


def test_shipped_names_are_recognised_in_every_spelling():
    assert shipped_name("weights/u4d.pt") == "u4d.pt"
    assert shipped_name("u4d.pt") == shipped_name("u4d") == "u4d.pt"
    assert shipped_name("weights/not_shipped.pt") is None
    assert shipped_name("weights/u4d_stage1.pt") is None  # the two-net U4D's files are shipped no more
    assert shipped_name("runs/weights/u4d.pt") is None  # another folder's file of that name
    assert shipped_name("/abs/weights/u4d.pt") is None


def test_a_shipped_name_resolves_to_the_checkout_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(WEIGHTS_ENV, "")  # recorded, so what main sets is undone
    assert resolve_weights("weights/u4d.pt") == CHECKOUT_DIR / "u4d.pt"
    (tmp_path / "weights").mkdir()
    (tmp_path / "weights" / "u4d.pt").write_bytes(b"mine")  # a path that exists is used as written
    assert resolve_weights("weights/u4d.pt") == Path("weights/u4d.pt")
    assert resolve_weights("runs/missing.pt") == Path("runs/missing.pt")  # not a shipped name: unchanged


def test_the_explicit_folder_comes_first_then_checkout_then_cache(no_installed, monkeypatch):
    cache = no_installed / "cache" / "u4d" / "weights"
    assert search_dirs() == [no_installed / "no_checkout" / "weights", cache]
    cache.mkdir(parents=True)
    (cache / "baseline.pt").write_bytes(b"cached")
    assert resolve_weights("weights/baseline.pt") == cache / "baseline.pt"
    explicit = no_installed / "mine"
    explicit.mkdir()
    (explicit / "baseline.pt").write_bytes(b"explicit")
    monkeypatch.setenv(WEIGHTS_ENV, str(explicit))
    assert search_dirs()[0] == explicit and resolve_weights("weights/baseline.pt") == explicit / "baseline.pt"


def test_weights_dir_is_taken_out_of_the_command_line_anywhere(monkeypatch):
    monkeypatch.setenv(WEIGHTS_ENV, "")  # recorded, so what main sets is undone
    assert split_weights_dir(["generate", "--weights-dir", "/w", "x", "--", "--weights-dir"]) == [
        "generate",
        "x",
        "--",
        "--weights-dir",
    ]
    import os

    assert os.environ[WEIGHTS_ENV] == "/w"
    assert split_weights_dir(["--weights-dir=/v", "info"]) == ["info"] and os.environ[WEIGHTS_ENV] == "/v"
    with pytest.raises(InputError, match="--weights-dir: expected a folder"):
        split_weights_dir(["info", "--weights-dir"])


def test_generate_without_installed_nets_says_how_to_get_them(no_installed, capsys):
    argv = ["generate", "u4d/generate_hdl64", "--out", str(no_installed / "bank"), "mode=baseline", "num=1"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: weights/baseline.pt: baseline checkpoint not found (a shipped net, not installed")
    assert "`u4d weights install PATH`" in err and err.count("\n") == 0 and not (no_installed / "bank").exists()
