"""benchmarks/bank_confidence.py on a toy world: a bank holding the very unlabelled scans is seen exactly as they are,
a bank of other scans is not, the shares are proportions, and a bad --bank names itself."""

from __future__ import annotations

import json
import shutil

import pytest

from tests.tiny_nets import SEG_TINY, load_script
from tests.tiny_worlds import write_toy_root
from u4d_aug.cli import main as u4d_main
from u4d_aug.errors import InputError

bank_confidence = load_script("bank_confidence")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A toy root, a 4-step checkpoint trained on all of its labels (the unlabelled split is then every scan), a bank
    that copies those scans without labels and a bank of other scans."""
    base = tmp_path_factory.mktemp("bank_confidence")
    root = write_toy_root(base / "root", frames=2)
    assert u4d_main(["seg-train", str(SEG_TINY), f"data.root={root}", "optim.steps=4", "eval_every=4",
                     "--out", str(base / "seg"), "--no-progress", "--quiet"]) == 0  # fmt: skip
    same = base / "same"
    shutil.copytree(root / "sequences" / "00" / "velodyne", same / "sequences" / "00" / "velodyne")
    other = write_toy_root(base / "other", sequences=("00",), frames=2, seed=7)
    return {"root": root, "ckpt": base / "seg" / "model.pt", "same": same, "other": other, "base": base}


def test_a_bank_of_the_same_scans_is_seen_as_they_are(world, tmp_path):
    out = tmp_path / "out"
    argv = ["--checkpoint", str(world["ckpt"]), "--real", str(world["root"]), "--bank", f"same={world['same']}",
            "--bank", f"other={world['other']}", "--scans", "2", "--out", str(out), "--no-progress"]  # fmt: skip
    assert bank_confidence.main(argv) == 0
    result = json.loads((out / "bank_confidence.json").read_text())
    real, same, other = (result["sources"][n]["mean"] for n in ("real unlabelled", "same", "other"))
    for key in ("kept", "confidence", "entropy"):
        assert same[key] == pytest.approx(real[key], rel=1e-6), key
        assert 0.0 <= real[key] <= 1.0
    assert same["kept_class_share"] == pytest.approx(real["kept_class_share"])
    assert other["confidence"] != pytest.approx(real["confidence"], rel=1e-6)  # other scans, other confidences
    assert real["kept_accuracy"] is not None and same["kept_accuracy"] is None  # the copy has no labels
    assert result["sources"]["real unlabelled"]["per_checkpoint"][0]["scans"] == 2
    if real["kept"] > 0:
        assert sum(real["kept_class_share"]) == pytest.approx(1.0)
    assert (out / "bank_confidence.png").stat().st_size > 0 and (out / "bank_confidence_examples.png").is_file()
    assert "| same |" in (out / "bank_confidence.md").read_text()


def test_a_constant_intensity_reaches_the_teacher(world, tmp_path):
    base = ["--checkpoint", str(world["ckpt"]), "--real", str(world["root"]), "--bank", f"same={world['same']}",
            "--scans", "2", "--no-progress"]  # fmt: skip
    results = []
    for extra in ([], ["--intensity", "0.9"]):
        out = tmp_path / str(len(extra))
        assert bank_confidence.main(base + ["--out", str(out)] + extra) == 0
        results.append(json.loads((out / "bank_confidence.json").read_text()))
    own, flat = results
    assert own["intensity"] is None and flat["intensity"] == 0.9
    flat_real, flat_same = (flat["sources"][n]["mean"] for n in ("real unlabelled", "same"))
    assert flat_same["confidence"] == pytest.approx(flat_real["confidence"], rel=1e-6)
    assert flat_real["confidence"] != pytest.approx(own["sources"]["real unlabelled"]["mean"]["confidence"], rel=1e-6)


def test_evenly_spaced_picks():
    assert bank_confidence.evenly_spaced(3, 5) == [0, 1, 2]
    assert bank_confidence.evenly_spaced(10, 3) == [0, 4, 9]  # 4.5 rounds to even


def test_bad_inputs_are_named_in_one_line(world, tmp_path, capsys):
    for text, match in (("nameonly", "NAME=DIR"), (f"x={tmp_path / 'absent'}", "absent is not a folder")):
        with pytest.raises(InputError, match=match):
            bank_confidence.parse_banks([text])
    (tmp_path / "file").write_text("")
    cases = [
        (["--checkpoint", str(tmp_path / "none.pt"), "--real", str(world["root"])], "none.pt"),
        (["--checkpoint", str(world["ckpt"]), "--real", str(tmp_path / "nowhere")], "nowhere"),
        (["--checkpoint", str(world["ckpt"]), "--real", str(world["root"]), "--scans", "0"], "--scans"),
    ]
    for argv, named in cases:
        assert bank_confidence.main(argv + ["--out", str(tmp_path / "o"), "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and named in err and "\n" not in err, err
    argv = ["--checkpoint", str(world["ckpt"]), "--real", str(world["root"]), "--out", str(tmp_path / "file")]
    assert bank_confidence.main(argv) == 2
    assert "is a file" in capsys.readouterr().err
