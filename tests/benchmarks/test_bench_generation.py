"""benchmarks/bench_generation.py: two sampler settings on tiny untrained nets: json keys, ratios from rows."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.tiny_nets import load_script, save_checkpoint
from u4d_aug.data.formats import write_kitti_scan
from u4d_aug.errors import InputError

bench = load_script("bench_generation")


def run_one_thread(argv: list[str]) -> int:
    """bench.main on one torch thread (the setting the benchmark is run with), restoring the count after."""
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        return bench.main(argv)
    finally:
        torch.set_num_threads(threads)


def test_two_samplers_write_methods_and_ratios(tmp_path):
    rng = np.random.default_rng(0)
    for seq in ("00", "01"):
        for i in range(3):
            points = np.concatenate([rng.uniform(-30, 30, (2000, 3)), rng.uniform(0, 1, (2000, 1))], 1)
            write_kitti_scan(tmp_path / "real" / "sequences" / seq / "velodyne" / f"{i:06d}.bin", points.astype("f4"))
    stages = ("stage1", "stage2", "baseline")
    nets = {
        stage: save_checkpoint(tmp_path / f"{stage}.pt", overrides=(f"diffusion.stage={stage}",)) for stage in stages
    }
    out = tmp_path / "gen.json"
    argv = ["--root", str(tmp_path / "real"), "--stage1", str(nets["stage1"]), "--stage2", str(nets["stage2"])]
    argv += ["--baseline", str(nets["baseline"]), "--reference", "00", "--floor", "01", "--num", "2"]
    argv += ["--seeds", "0", "1", "--samplers", "dpmpp2m:2:1", "ddpm:2:1", "--metrics", "points,rangejs"]
    argv += ["--work", str(tmp_path / "work"), "--out", str(out), "--device", "cpu"]
    assert run_one_thread(argv) == 0
    result = json.loads(out.read_text())
    assert list(result["samplers"]) == ["dpmpp2m_2_1", "ddpm_2_1"]
    assert result["methods"] == result["samplers"]["dpmpp2m_2_1"]["methods"]  # the first setting is the headline
    for block in result["samplers"].values():
        methods = block["methods"]
        assert set(methods) == {"u4d", "baseline", "floor"}
        for name in methods:
            for metric in ("points", "rangejs"):
                values = methods[name][metric]["values"]
                assert len(values) == 2 and methods[name][metric]["mean"] == pytest.approx(np.mean(values))
        points = methods["u4d"]["points"]["mean"] / methods["floor"]["points"]["mean"]
        assert block["ratios"]["u4d points/floor"] == pytest.approx(points)
        assert methods["floor"]["points"]["mean"] == 2000  # real scans keep their points
        # ... and hold fewer once projected to the nets' range image (at most one point per pixel)
        cfg = torch.load(nets["baseline"], weights_only=True)["config"]
        projected = methods["floor"]["points_projected"]
        assert len(projected["values"]) == 2 and 0 < projected["mean"] <= min(2000, cfg["height"] * cfg["width"])
        assert block["ratios"]["baseline points/floor projected"] == pytest.approx(
            methods["baseline"]["points"]["mean"] / projected["mean"]
        )
    # the floor is the same real scans for both settings; the banks of each setting are their own
    assert result["samplers"]["ddpm_2_1"]["methods"]["floor"] == result["methods"]["floor"]
    assert (tmp_path / "work" / "u4d_ddpm_2_1_s1").is_dir() and (tmp_path / "work" / "baseline_dpmpp2m_2_1_s0").is_dir()
    # neither FRD/FPD/JSD/MMD was asked for: no headline-over-DDPM ratios (`sampler_ratios_of` is tested alone)
    assert result["sampler_ratios"] == {}
    text = out.with_suffix(".md").read_text()
    assert "## dpmpp2m 2 steps (stage 1: 1)" in text and "u4d points/floor" in text
    assert "projected to the generators' range image" in text


def test_bad_sampler_setting_is_refused(capsys):
    with pytest.raises(SystemExit):
        bench.main(["--root", "x", "--stage1", "a", "--stage2", "b", "--baseline", "c", "--samplers", "ddpm:x"])
    assert "expected NAME:STEPS:STAGE1_STEPS" in capsys.readouterr().err


def test_a_two_net_u4d_names_both_stages_in_place_of_the_one_net(capsys):
    """--net defaults to the shipped one net weights/u4d.pt; --stage1 and --stage2 replace it together."""
    for two_net in (["--stage1", "a"], ["--stage2", "b"], ["--net", "n", "--stage1", "a", "--stage2", "b"]):
        with pytest.raises(SystemExit):
            bench.main(["--root", "x", *two_net])
        assert "--stage1 and --stage2 name a two-net U4D together, in place of --net" in capsys.readouterr().err


def test_mean_start_banks_are_their_own_and_recorded(tmp_path):
    """--mean-start-below: the banks carry it in their manifest, sit beside (not over) the plain ones, json says so."""
    from tests.tiny_worlds import write_tiny_world

    world, probs = tmp_path / "world", tmp_path / "probs"
    write_tiny_world(world, probs, num_scans=4, num_points=2000)
    for i in range(2):  # the floor's and reference's real scans: sequences 01 and 02 of the same tiny world
        for seq in ("01", "02"):
            source = world / "sequences" / "00" / "velodyne" / f"{i:06d}.bin"
            target = world / "sequences" / seq / "velodyne" / f"{i:06d}.bin"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(source.read_bytes())
            prob = probs / "sequences" / seq / "probs" / f"{i:06d}.npy"
            prob.parent.mkdir(parents=True, exist_ok=True)
            prob.write_bytes((probs / "sequences" / "00" / "probs" / f"{i:06d}.npy").read_bytes())
    nets = {s: save_checkpoint(tmp_path / f"{s}.pt", overrides=(f"diffusion.stage={s}",)) for s in ("stage1", "stage2")}
    nets["baseline"] = save_checkpoint(tmp_path / "baseline.pt", overrides=("diffusion.stage=baseline",))
    out = tmp_path / "gen.json"
    argv = ["--root", str(world), "--stage1", str(nets["stage1"]), "--stage2", str(nets["stage2"])]
    argv += ["--baseline", str(nets["baseline"]), "--reference", "01", "--floor", "02", "--num", "1", "--seeds", "0"]
    argv += ["--samplers", "ddpm:2:1", "--metrics", "points", "--work", str(tmp_path / "work"), "--out", str(out)]
    argv += ["--device", "cpu", "--mean-start-below", "-10", "--mean-data-root", str(world)]
    argv += ["--mean-probs-root", str(probs)]
    assert run_one_thread(argv) == 0
    assert json.loads(out.read_text())["mean_start_below"] == -10.0
    for method in ("u4d", "baseline"):
        manifest = json.loads((tmp_path / "work" / f"{method}_ddpm_2_1_ms-10_s0" / "manifest.json").read_text())
        assert manifest["sampling"]["mean_start_below"] == -10.0 and manifest["complete"]
    assert "Mean start: the nets' training mean image as x0 below log-SNR -10." in out.with_suffix(".md").read_text()


def test_sampler_ratios_divide_the_headline_by_each_other_setting():
    def block(u4d, baseline):
        return {"methods": {"u4d": {"frd": {"mean": u4d}}, "baseline": {"frd": {"mean": baseline}}}}

    blocks = {"fast": block(110.0, 90.0), "ddpm": block(100.0, 100.0), "ddim": block(None, 45.0)}
    ratios = bench.sampler_ratios_of(blocks, "fast", ("frd", "points"))
    assert ratios == {
        "u4d frd fast/ddpm": pytest.approx(1.1),
        "baseline frd fast/ddpm": pytest.approx(0.9),
        "u4d frd fast/ddim": None,  # a missing score gives no ratio
        "baseline frd fast/ddim": pytest.approx(2.0),
    }


def test_structure_metrics_score_every_bank_and_the_projected_floor(tmp_path, monkeypatch):
    """teacher, bev_density, roughness: per method and seed, the floor also after the generators' range image; the
    teacher's view is `teacher_view` (here a stand-in: a net on every point of the scans), kept keys stay."""
    rng = np.random.default_rng(0)
    for seq in ("00", "01"):
        for i in range(2):
            points = np.concatenate([rng.uniform(-30, 30, (3000, 3)), rng.uniform(0, 1, (3000, 1))], 1)
            points[:, 2] = rng.uniform(-2, 3, 3000)
            write_kitti_scan(tmp_path / "real" / "sequences" / seq / "velodyne" / f"{i:06d}.bin", points.astype("f4"))
    seen = []

    def fake_view(model, cfg, scans):
        seen.append(len(scans))
        return {"kept_share": 0.5, "building_share": 0.25, "class_share": {"road": 0.75, "building": 0.25}}

    monkeypatch.setattr(bench, "teacher_view", fake_view)
    monkeypatch.setattr(bench, "load_teacher", lambda path: (None, None))
    nets = {s: save_checkpoint(tmp_path / f"{s}.pt", overrides=(f"diffusion.stage={s}",)) for s in ("stage1", "stage2")}
    nets["baseline"] = save_checkpoint(tmp_path / "baseline.pt", overrides=("diffusion.stage=baseline",))
    out = tmp_path / "gen.json"
    argv = ["--root", str(tmp_path / "real"), "--stage1", str(nets["stage1"]), "--stage2", str(nets["stage2"])]
    argv += ["--baseline", str(nets["baseline"]), "--reference", "00", "--floor", "01", "--num", "2", "--seeds", "0"]
    argv += ["--samplers", "ddpm:2:1", "--metrics", "points,teacher,bev_density,roughness", "--teacher", "t.pt"]
    argv += ["--work", str(tmp_path / "work"), "--out", str(out), "--device", "cpu"]
    assert run_one_thread(argv) == 0
    result = json.loads(out.read_text())
    assert set(result["methods"]) == {"u4d", "baseline", "floor", "floor_projected"}
    assert seen == [2, 2, 2, 2]  # u4d, baseline, floor, floor projected: each bank's 2 scans
    for name, row in result["methods"].items():
        assert row["points"]["mean"] is not None, name  # the existing keys stay
        assert row["teacher_kept_share"]["mean"] == 0.5 and row["teacher_building_share"]["values"] == [0.25]
        assert row["teacher_class_share"] == {"road": 0.75, "building": 0.25}
        for key in ("bev_points_per_cell", "ring_roughness", "vertical_roughness"):
            assert row[key]["mean"] is not None and row[key]["mean"] > 0, (name, key)
    floor, projected = result["methods"]["floor"], result["methods"]["floor_projected"]
    assert projected["points"]["mean"] < floor["points"]["mean"]  # at most one point per pixel of the nets' image
    assert projected["points"]["mean"] == pytest.approx(floor["points_projected"]["mean"], abs=2)
    assert result["ratios"]["baseline/floor projected bev_points_per_cell"] == pytest.approx(
        result["methods"]["baseline"]["bev_points_per_cell"]["mean"] / projected["bev_points_per_cell"]["mean"]
    )
    text = out.with_suffix(".md").read_text()
    assert "| floor_projected |" in text and "points/BEV cell" in text and "vertical roughness" in text


def test_metric_names_are_checked_in_one_line():
    assert bench.parse_bench_metrics("frd, teacher,roughness") == ("frd", "teacher", "roughness")
    with pytest.raises(InputError, match="teacher,bev_density,roughness"):
        bench.parse_bench_metrics("frd,stars")


def test_floor_bank_refills_its_own_folder_and_refuses_one_another_draw_wrote(toy_root, tmp_path):
    out = tmp_path / "floor"
    bank = bench.floor_bank(toy_root, ["00", "01"], 3, 0, out)
    links = sorted((bank / "sequences" / "00" / "velodyne").iterdir())
    assert len(links) == 3 and all(link.is_symlink() for link in links)
    targets = [link.resolve() for link in links]
    links[1].unlink()  # an interrupted run: the same call completes the folder with the same scans
    bench.floor_bank(toy_root, ["00", "01"], 3, 0, out)
    assert [link.resolve() for link in sorted(links[0].parent.iterdir())] == targets
    seeds = [seed for seed in range(1, 20) if sorted(np.random.default_rng(seed).choice(6, 3, replace=False)) !=
             sorted(np.random.default_rng(0).choice(6, 3, replace=False))]  # fmt: skip
    with pytest.raises(InputError, match="pick another --work"):  # another draw into the same folder
        bench.floor_bank(toy_root, ["00", "01"], 3, seeds[0], out)
    (out / "sequences" / "00" / "velodyne" / "000000.bin").unlink()
    (out / "sequences" / "00" / "velodyne" / "000000.bin").write_bytes(b"x")
    with pytest.raises(InputError, match="did not write"):
        bench.floor_bank(toy_root, ["00", "01"], 3, 0, out)


def test_a_one_net_u4d_samples_both_stages_and_reports_its_budget(tmp_path):
    rng = np.random.default_rng(0)
    for seq in ("00", "01"):
        points = np.concatenate([rng.uniform(-30, 30, (2000, 3)), rng.uniform(0, 1, (2000, 1))], 1)
        write_kitti_scan(tmp_path / "real" / "sequences" / seq / "velodyne" / "000000.bin", points.astype("f4"))
    net = save_checkpoint(tmp_path / "u4d.pt", overrides=("diffusion.stage=u4d",), step=7)
    baseline = save_checkpoint(tmp_path / "baseline.pt", overrides=("diffusion.stage=baseline",))
    out = tmp_path / "gen.json"
    argv = ["--root", str(tmp_path / "real"), "--net", str(net), "--baseline", str(baseline), "--reference", "00"]
    argv += ["--floor", "01", "--num", "1", "--seeds", "0", "--samplers", "ddpm:2:1", "--metrics", "points"]
    argv += ["--work", str(tmp_path / "work"), "--out", str(out), "--device", "cpu"]
    assert run_one_thread(argv) == 0
    result = json.loads(out.read_text())
    assert set(result["training"]) == {"u4d", "baseline"}
    assert result["training"]["u4d"]["stage"] == "u4d" and result["training"]["u4d"]["steps"] == 7
    assert result["methods"]["u4d"]["points"]["mean"] > 0
    manifest = json.loads((tmp_path / "work" / "u4d_ddpm_2_1_s0" / "manifest.json").read_text())
    assert str(net) in json.dumps(manifest)


def test_a_cascade_scores_both_methods_through_one_detail_level(tmp_path):
    rng = np.random.default_rng(0)
    for seq in ("00", "01"):
        points = np.concatenate([rng.uniform(-30, 30, (4000, 3)), rng.uniform(0, 1, (4000, 1))], 1)
        write_kitti_scan(tmp_path / "real" / "sequences" / seq / "velodyne" / "000000.bin", points.astype("f4"))
    layout = ("height=64", "width=256", "row_mode=beam")
    net = save_checkpoint(tmp_path / "u4d.pt", overrides=("diffusion.stage=u4d", *layout))
    baseline = save_checkpoint(tmp_path / "baseline.pt", overrides=("diffusion.stage=baseline", *layout))
    out = tmp_path / "gen.json"
    argv = ["--root", str(tmp_path / "real"), "--net", str(net), "--baseline", str(baseline), "--reference", "00"]
    argv += ["--floor", "01", "--num", "1", "--seeds", "0", "--samplers", "ddpm:2:1", "--metrics", "points"]
    argv += ["--work", str(tmp_path / "work"), "--out", str(out), "--device", "cpu", "--detail", "nearest"]
    assert run_one_thread(argv) == 0
    result = json.loads(out.read_text())
    for method in ("u4d", "baseline"):
        manifest = json.loads((tmp_path / "work" / f"{method}_ddpm_2_1_s0" / "manifest.json").read_text())
        assert manifest["detail"] == "nearest" and (manifest["height"], manifest["width"]) == (64, 1024)
    # the floor is projected to the scans' 64x1024 image, not to the layout's 64x256
    (floor,) = (tmp_path / "work").glob("floor*")
    geometry = {"sensor": "hdl64", "height": 64, "width": 1024, "row_mode": "beam"}
    at_1024 = bench.projected_points(floor, geometry)
    assert result["methods"]["floor"]["points_projected"]["mean"] == at_1024
    assert at_1024 > bench.projected_points(floor, {**geometry, "width": 256})
