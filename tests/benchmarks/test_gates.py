"""benchmarks/gates.py on a toy world: the reference / real / real-projected rows, a bank holding the real-projected
scans scores as that row, the reference row has no distance to itself, bad input is one line."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tests.tiny_nets import SEG_TINY, load_script
from tests.tiny_worlds import write_toy_root
from u4d_aug.cli import main as u4d_main

gates = load_script("gates")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A toy root of 4 sequences x 2 scans and a 4-step tiny teacher trained on it."""
    base = tmp_path_factory.mktemp("gates")
    root = write_toy_root(base / "root", sequences=("00", "01", "02", "03"), frames=2)
    assert u4d_main(["seg-train", str(SEG_TINY), f"data.root={root}", "optim.steps=4", "eval_every=4",
                     "--out", str(base / "seg"), "--no-progress", "--quiet"]) == 0  # fmt: skip
    return {"root": root, "teacher": base / "seg" / "model.pt", "base": base}


def test_a_bank_of_the_real_projected_scans_scores_as_that_row(world, tmp_path):
    work = tmp_path / "work"
    argv = ["--real", str(world["root"]), "--real-sequences", "00-01", "--num", "3", "--teacher", str(world["teacher"]),
            "--metrics", "teacher,bev_density,roughness,jsd", "--work", str(work)]  # fmt: skip
    assert gates.main(argv + ["--out", str(tmp_path / "first.json")]) == 0
    first = json.loads((tmp_path / "first.json").read_text())
    assert first["floor_sequences"] == ["02", "03"] and list(first["rows"]) == ["reference", "real", "real projected"]
    bank = tmp_path / "bank"
    shutil.copytree(work / "real_projected_n3", bank)
    assert gates.main(argv + ["--bank", f"copy={bank}", "--out", str(tmp_path / "gates.json")]) == 0
    rows = json.loads((tmp_path / "gates.json").read_text())["rows"]
    keys = ("teacher_kept_share", "teacher_building_share", "bev_points_per_cell", "ring_roughness", "jsd")
    for key in (*keys, "vertical_roughness", "teacher_class_share"):
        assert rows["copy"][key] == pytest.approx(rows["real projected"][key]), key
    assert rows["copy"]["scans"] == 3 and 0.0 < rows["real"]["teacher_kept_share"] <= 1.0
    assert "jsd" not in rows["reference"] and rows["reference"]["bev_points_per_cell"] > 0  # no distance to itself
    assert rows["real projected"]["jsd"] > 0  # other scans than the reference's
    text = (tmp_path / "gates.md").read_text()
    assert "| copy |" in text and "| real projected |" in text and "building % of kept" in text
    assert "python benchmarks/gates.py --real" in text


def test_only_the_first_num_scans_of_a_bank_count(world, tmp_path):
    argv = ["--real", str(world["root"]), "--real-sequences", "00", "--floor-sequences", "01", "--num", "2",
            "--bank", f"big={world['root']}", "--metrics", "bev_density", "--work", str(tmp_path / "w"),
            "--out", str(tmp_path / "g.json")]  # fmt: skip
    assert gates.main(argv) == 0
    rows = json.loads((tmp_path / "g.json").read_text())["rows"]
    assert rows["big"]["scans"] == 2  # of the root's 8 scans: the first two, those of sequence 00
    assert rows["big"]["bev_points_per_cell"] == pytest.approx(rows["reference"]["bev_points_per_cell"])


def test_bad_input_is_one_line(world, tmp_path, capsys):
    base = ["--real", str(world["root"]), "--real-sequences", "00-03", "--out", str(tmp_path / "g.json")]
    cases = [(["--bank", "nameonly"], "NAME=DIR"), (["--metrics", "stars"], "bev_density"),
             ([], "no sequence left"), (["--num", "0"], "--num")]  # fmt: skip
    for extra, named in cases:
        assert gates.main(base + extra + ["--work", str(tmp_path / "w")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and named in err and "\n" not in err, err


def _autoencoder(path, seed):
    """An untrained tiny autoencoder for 64x1024 HDL-64E beam-row images (the gates' geometry)."""
    from u4d_aug.autoencoder_stage import AutoencoderTrainConfig, build_autoencoder, save_autoencoder
    from u4d_aug.nn.autoencoder import AutoencoderConfig

    cfg = AutoencoderTrainConfig(ae=AutoencoderConfig(base_channels=8, channel_multipliers=(1, 2), z_channels=4,
                                                      gn_groups=4))  # fmt: skip
    save_autoencoder(path, build_autoencoder(cfg.ae, seed), cfg)
    return path


def test_the_real_scans_through_an_autoencoder_are_a_row_of_their_own(world, tmp_path):
    first, second = _autoencoder(tmp_path / "a.pt", 0), _autoencoder(tmp_path / "b.pt", 1)
    work = tmp_path / "work"
    argv = ["--real", str(world["root"]), "--real-sequences", "00-01", "--num", "2", "--metrics", "bev_density",
            "--work", str(work), "--autoencoder", f"a={first}", "--autoencoder", f"b={second}",
            "--out", str(tmp_path / "g.json")]  # fmt: skip
    assert gates.main(argv) == 0
    result = json.loads((tmp_path / "g.json").read_text())
    assert list(result["rows"])[3:] == ["real autoencoded (a)", "real autoencoded (b)"]
    assert result["autoencoders"] == {"a": str(first), "b": str(second)}
    assert result["rows"]["real autoencoded (a)"]["scans"] == 2
    folders = sorted(p.name for p in work.glob("real_ae_*"))
    assert len(folders) == 2  # one per autoencoder file: a retrained one never reuses another's scans
    assert "| real autoencoded (a) |" in (tmp_path / "g.md").read_text()


def test_an_autoencoder_that_is_not_a_file_is_one_line(world, tmp_path, capsys):
    argv = ["--real", str(world["root"]), "--real-sequences", "00-01", "--autoencoder", f"a={tmp_path}",
            "--work", str(tmp_path / "w"), "--out", str(tmp_path / "g.json")]  # fmt: skip
    assert gates.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "NAME=FILE" in err and "\n" not in err


def test_the_real_layouts_completed_by_a_detail_net_are_a_row_of_their_own(world, tmp_path, capsys):
    from tests.tiny_nets import TINY
    from u4d_aug.config import load_config
    from u4d_aug.export_weights import export_weights
    from u4d_aug.stage import DiffusionTrainConfig
    from u4d_aug.train import train

    overrides = [f"data_root={world['root']}", "diffusion.stage=detail", "height=64", "width=1024", "row_mode=beam",
                 "steps=2", "batch_size=1", f"out={tmp_path / 'run'}"]  # fmt: skip
    train(load_config(DiffusionTrainConfig, TINY, overrides), progress=False)
    weights = tmp_path / "detail.pt"
    export_weights(tmp_path / "run", weights)
    work = tmp_path / "work"
    argv = ["--real", str(world["root"]), "--real-sequences", "00-01", "--num", "2", "--metrics", "bev_density",
            "--work", str(work), "--detail", f"d={weights}", "--layout-nearest", "4",
            "--out", str(tmp_path / "g.json")]  # fmt: skip
    assert gates.main(argv) == 0
    result = json.loads((tmp_path / "g.json").read_text())
    assert list(result["rows"])[3:] == ["real layout nearest (1/4)", "real layout detailed (d)"]
    assert result["details"] == {"d": str(weights)}
    # the nearest row: every point of the quarter-width layout, 4 times (at the 4 azimuths of its column's bin)
    for path in sorted((work / "real_nearest_4_n2").glob("sequences/*/velodyne/*.bin")):
        ranges = np.sort(np.linalg.norm(np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3], axis=1))
        assert len(ranges) % 4 == 0
        np.testing.assert_allclose(ranges[::4], ranges[3::4], rtol=1e-5)
    assert result["rows"]["real layout detailed (d)"]["scans"] == 2
    (folder,) = work.glob("real_detail_*")
    assert len(list(folder.glob("sequences/*/velodyne/*.bin"))) == 2
    # a training checkpoint holds no training mean to start the default sampling from: one line naming the way out
    argv[argv.index(f"d={weights}")] = f"d={sorted((tmp_path / 'run' / 'checkpoints').glob('*.pt'))[-1]}"
    assert gates.main(argv) == 2
    assert "export the net with `u4d export-weights" in capsys.readouterr().err
    # a stride that does not divide the sensor's width names the option
    argv[argv.index("--detail") : argv.index("--detail") + 2] = []
    argv[argv.index("--layout-nearest") + 1] = "3"
    assert gates.main(argv) == 2
    assert capsys.readouterr().err.strip() == "error: --layout-nearest must be >= 2 and divide width 1024, got 3"
