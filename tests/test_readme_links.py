"""Every relative link of the README and of benchmarks/results/README.md names a file or folder that exists, and the
README's results summary stays one table of at most 10 rows."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("page", ["README.md", "benchmarks/results/README.md"])
def test_relative_links_resolve(page):
    path = REPO / page
    targets = {m for m in LINK.findall(path.read_text(encoding="utf-8")) if "://" not in m}
    missing = sorted(t for t in targets if not (path.parent / t).exists() and not t.startswith("../shared"))
    assert not missing, f"{page} links to missing files: {missing}"


def test_results_in_brief_is_one_short_table():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("## Results in brief", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ")]
    assert rows[0].startswith("| question | answer |") and 2 <= len(rows) - 1 <= 10
    assert not [line for line in section.splitlines() if line.startswith("- ")], "prose bullets belong in results/"
