"""benchmarks/diagnostics/mutations.py: every mutation still applies to today's source (its "before" text is there
once, its tensor is shipped), and applying one breaks its file as described; the test suite itself is not run."""

from __future__ import annotations

import shutil

import pytest
import torch

from tests.tiny_nets import REPO, load_script

script = load_script("diagnostics/mutations")


def test_the_five_breakages_of_issue_72_each_have_a_mutation():
    numbers = [mutation.number for mutation in script.MUTATIONS]
    assert len(set(numbers)) == len(numbers) and {number[0] for number in numbers} == {"1", "2", "3", "4", "5"}


@pytest.mark.parametrize("mutation", script.MUTATIONS, ids=lambda mutation: mutation.number)
def test_each_mutation_still_applies(mutation):
    assert script.check(mutation) is None
    assert all(test.startswith("tests/") and test.endswith(".py") for test in (*mutation.tests, *mutation.slow_tests))


@pytest.mark.parametrize("mutation", script.MUTATIONS, ids=lambda mutation: mutation.number)
def test_applying_a_mutation_changes_its_one_file(mutation, tmp_path):
    for name in (mutation.path, *mutation.tests, *mutation.slow_tests):  # the rest of a checkout is not read
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / name, tmp_path / name)
    script.apply(mutation, tmp_path)
    if mutation.kind == "text":
        text = (tmp_path / mutation.path).read_text(encoding="utf-8")
        original = (REPO / mutation.path).read_text(encoding="utf-8")
        assert text == original.replace(mutation.before, mutation.after) and text != original
    else:  # the tensor zeroed, the hash fields as shipped
        broken = torch.load(tmp_path / mutation.path, weights_only=True)
        shipped = torch.load(REPO / mutation.path, weights_only=True)
        assert not bool(broken["model"][mutation.before].any())
        assert (broken["hash"], broken["weights_hash"]) == (shipped["hash"], shipped["weights_hash"])
    with pytest.raises(ValueError, match=rf"mutation {mutation.number} \("):  # applied, it no longer applies
        script.apply(mutation, tmp_path)
