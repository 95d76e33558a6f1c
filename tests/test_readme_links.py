"""Every relative link of the README and of each markdown file under benchmarks/results/ names a file or folder that
exists, the README's results summary stays one table of at most 10 rows, and the results index fits one screen."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")
SHARED = REPO.parent / "shared"  # data beside the checkout, not part of it
RESULTS = REPO / "benchmarks" / "results"
QUESTIONS = ("downstream", "generation", "temporal", "world", "segmentation", "speed")
PAGES = ["README.md"] + sorted(str(p.relative_to(REPO)) for p in RESULTS.rglob("*.md"))


@pytest.mark.parametrize("page", PAGES)
def test_relative_links_resolve(page):
    path = REPO / page
    targets = {m for m in LINK.findall(path.read_text(encoding="utf-8")) if "://" not in m}
    missing = sorted(
        t for t in targets if not (path.parent / t).exists() and not (path.parent / t).resolve().is_relative_to(SHARED)
    )
    assert not missing, f"{page} links to missing files: {missing}"


def test_results_in_brief_is_one_short_table():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("## Results in brief", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ")]
    assert rows[0].startswith("| question | answer |") and 2 <= len(rows) - 1 <= 10
    assert not [line for line in section.splitlines() if line.startswith("- ")], "prose bullets belong in results/"


def test_results_index_is_one_screen_with_a_line_per_question():
    text = (RESULTS / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 40
    for folder in QUESTIONS:
        assert (RESULTS / folder / "README.md").is_file()
        assert sum(line.startswith(f"| [`{folder}/`]({folder}/README.md) |") for line in text.splitlines()) == 1
