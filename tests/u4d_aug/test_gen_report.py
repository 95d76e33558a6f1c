"""`u4d gen-report`: real vs U4D vs baseline PNG from tiny banks; bad bank arguments are named."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tiny_nets import gen_config
from tests.tiny_worlds import write_tiny_world
from u4d_aug.cli import main
from u4d_aug.errors import InputError
from u4d_aug.gen_report import bank_geometry, depth_image, gen_report
from u4d_aug.generate import generate_bank


def test_report_png_from_u4d_and_baseline_banks(untrained_checkpoints, tmp_path):
    world, probs = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(world, probs, num_scans=2)
    banks = {"u4d": tmp_path / "u4d", "baseline": tmp_path / "r2dm"}
    generate_bank(gen_config(untrained_checkpoints, "num=1", "mode=u4d"), banks["u4d"], progress=False)
    generate_bank(gen_config(untrained_checkpoints, "num=1", "mode=baseline"), banks["baseline"], progress=False)
    geometry = bank_geometry(banks["u4d"])
    assert (geometry.height, geometry.width, geometry.row_mode) == (16, 64, "linear")

    png = gen_report(world, banks, tmp_path / "cmp.png", probs_root=probs)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000

    status = main(["gen-report", str(world), "--bank", f"u4d={banks['u4d']}", "--png", str(tmp_path / "c.png")])
    assert status == 0 and (tmp_path / "c.png").is_file()
    with pytest.raises(InputError, match="manifest"):
        gen_report(world, {"u4d": world}, tmp_path / "x.png")


def test_report_shows_a_frame_of_sequence_banks(untrained_sequence_checkpoints, tmp_path):
    world = tmp_path / "world"
    write_tiny_world(world, tmp_path / "probs", num_scans=2)
    banks = {"u4d": tmp_path / "u4d", "baseline": tmp_path / "r2dm"}
    generate_bank(gen_config(untrained_sequence_checkpoints, "num=1", "mode=u4d"), banks["u4d"], progress=False)
    generate_bank(
        gen_config(untrained_sequence_checkpoints, "num=1", "mode=baseline"), banks["baseline"], progress=False
    )
    assert bank_geometry(banks["u4d"]).frames == 2

    first = gen_report(world, banks, tmp_path / "f0.png")
    second = gen_report(world, banks, tmp_path / "f1.png", frame=1)
    assert first.stat().st_size > 10_000 and first.read_bytes() != second.read_bytes()  # another frame is drawn
    with pytest.raises(InputError, match="--frame 2 outside"):
        gen_report(world, banks, tmp_path / "x.png", frame=2)


def test_depth_image_puts_points_at_their_range(tmp_path):
    from u4d_aug.data.sensors import get_sensor
    from u4d_aug.gen_report import Geometry

    geometry = Geometry(get_sensor("hdl64"), 16, 64, "linear")
    points = np.array([[10.0, 0.0, -1.0, 0.5], [0.0, 20.0, -1.0, 0.5]], dtype=np.float32)
    image = depth_image(points, geometry)
    assert np.isfinite(image).sum() == 2
    np.testing.assert_allclose(np.sort(image[np.isfinite(image)]), np.hypot([10.0, 20.0], 1.0), rtol=1e-5)


def test_bad_bank_argument_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["gen-report", str(tmp_path), "--bank", "no-equals-sign", "--png", str(tmp_path / "x.png")])
    assert "NAME=DIR" in capsys.readouterr().err


def test_comparison_figure_names_units_of_every_panel(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from u4d_aug.data.sensors import get_sensor
    from u4d_aug.gen_report import Geometry, plot_comparison

    figures = []
    monkeypatch.setattr("u4d_aug.viz.save_figure", lambda fig, path, dpi=110: figures.append(fig) or path)
    geometry = Geometry(get_sensor("hdl64"), 16, 64, "linear")
    rng = np.random.default_rng(0)
    real = np.column_stack([rng.uniform(-20, 20, (300, 2)), rng.uniform(-2, 0, 300), rng.uniform(0, 1, 300)])
    entropy = rng.uniform(0, np.log(19), (16, 64))
    m_u = (entropy > 2.5).astype(np.float32)
    stage1 = np.where(m_u > 0, rng.uniform(3, 40, (16, 64)), np.nan)
    plot_comparison(tmp_path / "c.png", real, {"u4d": real[:200], "baseline": real[100:]}, geometry, (entropy, m_u),
                    stage1)  # fmt: skip
    axes = figures[0].axes
    bars = [[child.get_ylabel() for child in ax.child_axes] for ax in axes]
    assert (
        bars == [["depth [m]"], ["H(p) [nats]"], ["depth [m]"], ["depth [m]"], ["depth [m]"]] + [["height z [m]"]] * 3
    )
    assert "P_u outlined" in axes[1].get_title() and "stage 1" in axes[2].get_title()
    for bev, name in zip(axes[5:], ("real", "u4d", "baseline")):
        assert bev.get_title().startswith(f"{name}: BEV") and "[m]" in bev.get_xlabel() and bev.get_aspect() == 1.0
    plt.close(figures[0])
