"""benchmarks/diagnostics/plot_sim_street_types.py: one bird's-eye panel per street type, written under tmp_path."""

from __future__ import annotations

import sys

from tests.tiny_nets import load_script

bench = load_script("diagnostics/plot_sim_street_types")


def test_writes_one_figure_of_every_street_type(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench, "RESULTS", tmp_path / "world")
    monkeypatch.setattr(sys, "argv", ["plot_sim_street_types.py", "--extent", "20"])
    assert bench.main() == 0
    figure = tmp_path / "world" / "sim_street_types.png"
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size > 10_000
    printed = capsys.readouterr().out
    for kind in bench.STREET_TYPES:
        count = int(printed.split(f"{kind}: ", 1)[1].split(" points", 1)[0])
        assert count > 1000
