"""benchmarks/diagnostics/plot_bev_folders.py: one BEV + range-image column per folder, written under tmp_path; bad
folders are one line."""

from __future__ import annotations

from tests.tiny_nets import load_script
from tests.tiny_worlds import write_toy_root

bench = load_script("diagnostics/plot_bev_folders")


def test_draws_one_column_per_folder(tmp_path, capsys):
    root = write_toy_root(tmp_path / "root", sequences=("00",), frames=2)
    png = tmp_path / "bev.png"
    assert bench.main(["--folder", f"a={root}", "--folder", f"b={root}", "--index", "1", "--png", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    printed = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in printed] == ["a", "b"] and "000001.bin" in printed[0]


def test_bad_folders_are_one_line(tmp_path, capsys):
    root = write_toy_root(tmp_path / "root", sequences=("00",), frames=1)
    cases = [(["--folder", "nameonly"], "NAME=DIR"), (["--folder", f"a={root}", "--index", "5"], "need more than"),
             ([], "at least one")]  # fmt: skip
    for extra, named in cases:
        assert bench.main([*extra, "--png", str(tmp_path / "x.png")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and named in err and "\n" not in err, err
