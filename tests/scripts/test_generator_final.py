"""scripts/generator_final.sh run end to end with the stand-in `u4d` (tests/scripts/stand_in.py): both methods segment
by segment at equal budgets, every call one the real commands accept, each milestone exported, sampled and scored, a
second run starts nothing; EXTRA reaches the training config (the data-scarce generators), AE switches to the
latent preset with the autoencoder's row beside the gates, and the cascade trains a detail net and samples finished
layout milestones through it."""

from __future__ import annotations

import subprocess
from pathlib import Path

from tests.scripts.stand_in import check_call, recorded_calls, stand_in_env
from tests.tiny_nets import REPO

SCRIPT = REPO / "scripts" / "generator_final.sh"


def run_queue(env: dict) -> None:
    done = subprocess.run(["bash", str(SCRIPT)], cwd=REPO, env=env, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-3000:]


def trained_runs(calls: list[list[str]], runs: Path) -> list[tuple]:
    """(stage, steps, run folder) of each train-diffusion call; checks every call against the real parsers."""
    trained = []
    for argv in calls:
        if argv[0] == "py":
            assert argv[1] == "benchmarks/gates.py"
            continue
        args, cfg = check_call(argv, REPO)
        if argv[0] == "train-diffusion":
            trained.append((cfg.diffusion.stage, cfg.steps, args.out.relative_to(runs).as_posix(), cfg))
        elif argv[0] == "generate":
            sampled = cfg.baseline if cfg.mode == "baseline" else cfg.net  # baseline mode ignores the preset's net
            assert cfg.num == 16 and sampled.startswith(str(runs))
        else:
            assert argv[0] == "export-weights", argv
    return trained


def test_both_methods_alternate_at_equal_budgets_and_a_rerun_starts_nothing(tmp_path):
    runs = tmp_path / "runs"
    env = stand_in_env(tmp_path, RUNS=str(runs), METHOD="both", STEPS="4", SEGMENT="2")
    run_queue(env)
    calls = recorded_calls(tmp_path)
    trained = trained_runs(calls, runs)
    assert [t[:3] for t in trained] == [
        ("u4d", 2, "final/u4d"), ("baseline", 2, "final/baseline"), ("u4d", 4, "final/u4d"),
        ("baseline", 4, "final/baseline"),
    ]  # fmt: skip
    u4d_cfg = trained[0][3]
    assert u4d_cfg.diffusion.cond_noise == 0.05 and u4d_cfg.diffusion.min_snr_gamma is None
    assert u4d_cfg.probs_root == "data/sim_seg_probs" and u4d_cfg.sequences == ["00-87"]
    gates = [argv for argv in calls if argv[0] == "py"]
    assert len(gates) == 4 and not any("--autoencoder" in argv for argv in gates)
    assert (runs / "final" / "u4d_milestones").is_dir()
    run_queue(env)
    assert recorded_calls(tmp_path) == calls  # everything there: no call


def test_extra_overrides_reach_the_training_config_in_their_own_folder(tmp_path):
    runs = tmp_path / "runs"
    extra = 'sequences=["05","11"] probs_root=data/scarce_probs'
    env = stand_in_env(tmp_path, RUNS=str(runs), NAME="scarce", METHOD="u4d", STEPS="2", SEGMENT="2", EXTRA=extra)
    run_queue(env)
    (trained,) = trained_runs(recorded_calls(tmp_path), runs)
    stage, steps, folder, cfg = trained
    assert (stage, steps, folder) == ("u4d", 2, "scarce/u4d")
    assert cfg.sequences == ["05", "11"] and cfg.probs_root == "data/scarce_probs"


def test_an_autoencoder_switches_to_the_latent_preset_with_its_gates_row(tmp_path):
    runs = tmp_path / "runs"
    ae = tmp_path / "ae" / "autoencoder.pt"
    ae.parent.mkdir()
    ae.write_bytes(b"")
    env = stand_in_env(tmp_path, RUNS=str(runs), AE=str(ae), NAME="p", METHOD="both", STEPS="2", SEGMENT="2",
                       EXTRA="net.base_channels=16")  # fmt: skip
    run_queue(env)
    calls = recorded_calls(tmp_path)
    trained = trained_runs(calls, runs)
    assert [t[:3] for t in trained] == [("u4d", 2, "latent/p/u4d"), ("baseline", 2, "latent/p/baseline")]
    for argv in calls:
        if argv[0] == "train-diffusion":
            assert Path(argv[1]) == Path("configs/u4d/latent_hdl64.yaml")
    cfg = trained[0][3]
    assert cfg.autoencoder == str(ae) and cfg.latent_factor == 4 and cfg.net.base_channels == 16
    assert cfg.diffusion.cond_noise == 0.1
    gates = [argv for argv in calls if argv[0] == "py"]
    assert len(gates) == 2 and all(f"ae={ae}" in argv for argv in gates)


def test_the_cascade_trains_a_detail_net_and_reruns_a_layout_run_through_it(tmp_path):
    runs = tmp_path / "runs"
    detail = "detail_stride=4 crop_width=256 crop_margin=16"
    env = stand_in_env(tmp_path, RUNS=str(runs), NAME="c", METHOD="detail", STEPS="2", SEGMENT="2", EXTRA=detail)
    run_queue(env)
    calls = recorded_calls(tmp_path)
    (trained,) = trained_runs(calls, runs)
    stage, steps, folder, cfg = trained
    assert (stage, steps, folder) == ("detail", 2, "c/detail") and cfg.detail_stride == 4
    assert cfg.diffusion.cond_noise == 0.05 and cfg.crop_margin == 16
    assert [argv[0] for argv in calls] == ["train-diffusion", "export-weights"]  # no bank without a layout

    layout = "height=64 width=256 crop_width=0"
    env = stand_in_env(tmp_path, RUNS=str(runs), NAME="c", METHOD="baseline", STEPS="2", SEGMENT="2", EXTRA=layout)
    run_queue(env)
    before = len(recorded_calls(tmp_path))
    weights = runs / "c" / "detail_milestones" / "step_2.pt"
    run_queue({**env, "DETAIL": str(weights)})
    added = recorded_calls(tmp_path)[before:]
    assert [argv[0] for argv in added] == ["generate", "py"]  # the trained layout net, only sampled through it
    assert f"detail={weights}" in added[0] and "--out" in added[0]
    assert added[0][added[0].index("--out") + 1].endswith("baseline_milestones/cascade_bank_2")
    assert added[1][-1].endswith("baseline_milestones/cascade_gates_2.json")
    assert f"cascade_baseline_2={added[0][added[0].index('--out') + 1]}" in added[1]
