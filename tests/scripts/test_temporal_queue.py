"""scripts/temporal_queue.sh run end to end with the stand-in `u4d` (tests/scripts/stand_in.py): every call is one
the real commands accept, the budgets are equal, the table comes out of the real
benchmarks/reports/temporal_table.py, and a second run starts nothing; two queues share one task list through claims;
ONE_NET=1 trains U4D as one net from SOURCE_U4D on its source's loss, at the baseline's budget, into its own table."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.scripts.stand_in import check_call, recorded_calls, run_both, stand_in_env
from tests.tiny_nets import REPO, TINY, save_checkpoint

SCRIPT = REPO / "scripts" / "temporal_queue.sh"


@pytest.fixture
def queue_env(tmp_path: Path) -> dict:
    """RUNS / DATA / RESULTS in tmp_path with the held-out places 88-99; the real interpreter for the table."""
    for seq in range(88, 100):
        (tmp_path / "data" / "sim_seg" / "sequences" / str(seq)).mkdir(parents=True)
    folders = {name: str(tmp_path / name.lower()) for name in ("RUNS", "DATA", "RESULTS")}
    # the two-net mode's stage nets (the shipped U4D is one net); the stand-in never reads them
    stages = tmp_path / "two_net"
    stages.mkdir()
    for stage in ("stage1", "stage2"):
        (stages / f"u4d_{stage}.pt").write_bytes(b"stand-in")
    return stand_in_env(tmp_path, STEPS="20", WAIT="0.1", PY=sys.executable, SOURCE_STAGES=str(stages), **folders)


def option(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def test_every_call_is_valid_budgets_are_equal_and_the_table_is_written(queue_env, tmp_path):
    run_both(SCRIPT, REPO, queue_env)
    made = recorded_calls(tmp_path)
    steps: dict[str, int] = {}
    for argv in made:
        args, cfg = check_call(argv, REPO)
        if argv[0] == "train-diffusion":
            assert args.config == Path("configs/u4d/cpu_hdl64_most.yaml")
            source = Path(cfg.init_from) if cfg.diffusion.stage != "baseline" else REPO / cfg.init_from
            assert source.is_file(), cfg.init_from  # SOURCE_STAGES' net of this stage, the shipped baseline
            assert cfg.diffusion.stage == "baseline" or source.parent == tmp_path / "two_net"
            assert Path(cfg.init_from).stem.endswith(cfg.diffusion.stage)
            assert cfg.data_root == f"{tmp_path}/data/sim_seg" and cfg.frames == 4
            steps[str(args.out)] = cfg.steps
        elif argv[0] == "generate":
            assert cfg.frames == 5 and cfg.num == 24  # TTCE k = 4 needs 5 frames
        elif argv[0] == "evaluate":
            assert args.real_sequences == ["88-99"] and args.json
            assert args.out.parent == tmp_path / "results" / "temporal_evals"  # committed beside the table
        elif argv[0] == "seg-predict":  # the world's uncertainty, once, from the shipped segmentor
            assert args.checkpoint == Path("weights/uncertainty_segmentor.pt") and args.sequences == ["00-87"]
        else:
            assert argv[0] in ("gates", "simulate"), argv

    runs = tmp_path / "runs" / "temporal"
    u4d_methods = [f"{m}_s{s}" for m in ("u4d_most", "u4d_no_temporal") for s in (0, 1)]
    u4d_methods += [f"fusion_{v}_s0" for v in ("cascade", "add", "concat")]
    for name in u4d_methods:  # U4D's two stages together get the baseline's budget
        total = steps[str(runs / name / "stage1")] + steps[str(runs / name / "stage2")]
        assert total == steps[str(runs / "baseline_most_s0")] == steps[str(runs / "baseline_most_s1")] == 40
    fusions = {
        option(a, "--out"): next(x for x in a if x.startswith("net.most_fusion="))
        for a in made
        if a[0] == "train-diffusion" and "fusion_" in option(a, "--out")
    }
    assert sorted(set(fusions.values())) == ["net.most_fusion=add", "net.most_fusion=cascade", "net.most_fusion=concat"]
    no_temporal = [a for a in made if a[0] == "train-diffusion" and "u4d_no_temporal" in option(a, "--out")]
    assert len(no_temporal) == 4 and all("net.most=false" in a for a in no_temporal)

    floor = runs / "floor" / "sequences"
    assert sorted(p.name for p in floor.iterdir()) == [str(s) for s in range(88, 100)]
    table = json.loads((tmp_path / "results" / "temporal.json").read_text())
    assert set(table["methods"]) == {"u4d_most", "baseline_most", "u4d_no_temporal", "floor"}
    assert table["methods"]["u4d_most"]["seeds"] == 2 and table["methods"]["floor"]["seeds"] == 1
    assert set(table["fusion"]) == {"gating", "cascade", "add", "concat"}
    evals = tmp_path / "results" / "temporal_evals"
    gates = [(a[1], option(a, "--png")) for a in made if a[0] == "gates"]  # the trained model's two stages
    results = tmp_path / "results"
    assert gates == [
        (f"{runs}/u4d_most_s0/stage2", f"{results}/most_gates.png"),
        (f"{runs}/u4d_most_s0/stage1", f"{results}/most_gates_stage1.png"),
    ]
    budget = json.loads((evals / "u4d_most_s1" / "budget.json").read_text())
    assert budget["nets"] == {"stage1": {"steps": 20, "minutes": 20.0}, "stage2": {"steps": 20, "minutes": 20.0}}
    assert budget["host"]["cores"] >= 1 and budget["host"]["torch_threads"] == 1
    assert [a[0] for a in made].count("seg-predict") == 1

    (tmp_path / "calls.jsonl").unlink()
    run_both(SCRIPT, REPO, queue_env)
    assert recorded_calls(tmp_path) == []  # every method has its evaluation: nothing runs again

    # a new machine: no run folders, no probabilities, only the committed evaluations: nothing trains again
    shutil.rmtree(tmp_path / "runs")
    shutil.rmtree(tmp_path / "data" / "sim_seg_probs")
    run_both(SCRIPT, REPO, queue_env)
    assert [a[0] for a in recorded_calls(tmp_path)] == ["seg-predict"]


def test_propagate_reuses_the_trained_nets_and_writes_its_own_table(queue_env, tmp_path):
    run_both(SCRIPT, REPO, queue_env)
    runs = tmp_path / "runs" / "temporal"
    shutil.rmtree(runs / "baseline_most_s0")  # a net that is not on this machine is trained
    (tmp_path / "calls.jsonl").unlink()
    run_both(SCRIPT, REPO, {**queue_env, "PROPAGATE": "1"})
    made = recorded_calls(tmp_path)
    trained = [option(a, "--out") for a in made if a[0] == "train-diffusion"]
    assert trained == [str(runs / "baseline_most_s0")]
    generated = [a for a in made if a[0] == "generate"]
    assert len(generated) == 9 and all("propagate=true" in a for a in generated)
    assert all(check_call(a, REPO)[1].propagate and "_prop_s" in option(a, "--out") for a in generated)
    scored = [option(a, "--out") for a in made if a[0] == "evaluate"]
    results = tmp_path / "results"
    assert len(scored) == 9 and all(Path(o).parent == results / "temporal_evals_propagated" for o in scored)
    assert not [a for a in made if a[0] == "gates"]  # the gate figures are of the nets, drawn once
    table = json.loads((results / "temporal_propagated.json").read_text())
    assert table["methods"]["u4d_most"]["seeds"] == 2 and table["methods"]["floor"]["seeds"] == 1  # the one floor
    assert set(table["fusion"]) == {"gating", "cascade", "add", "concat"}


def test_the_two_net_mode_names_its_missing_stage_nets(queue_env, tmp_path):
    env = {**queue_env, "CORE": "A", "SOURCE_STAGES": str(tmp_path / "nowhere")}
    done = subprocess.run(["bash", str(SCRIPT)], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "nowhere/u4d_stage1.pt" in done.stderr and "ONE_NET=1" in done.stderr


def test_the_script_needs_a_core(queue_env):
    env = {k: v for k, v in queue_env.items() if k != "CORE"}
    result = subprocess.run(["bash", str(SCRIPT)], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode != 0 and "set CORE=A or CORE=B" in result.stderr


def test_claims_of_ended_queues_are_taken_over_and_a_live_claim_is_left_alone(queue_env, tmp_path):
    claims = tmp_path / "runs" / "temporal" / "claims"
    claims.mkdir(parents=True)
    boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    ended = subprocess.Popen(["true"])
    ended.wait()
    (claims / "world").write_text("an-earlier-boot 1\n")  # pid 1 lives, but on another boot: an ended queue
    (claims / "stage_u4d_most_0_stage1").write_text(f"{boot} {ended.pid}\n")  # this boot, the pid has ended
    (claims / "floor").write_text(f"{boot} {os.getpid()}\n")  # this boot, alive: a queue still scoring the floor
    procs = [
        subprocess.Popen(
            ["bash", str(SCRIPT)],
            cwd=REPO,
            env={**queue_env, "CORE": core},
            text=True,
            stdout=subprocess.DEVNULL,
            stderr=(tmp_path / f"queue_{core}.err").open("w"),  # a file: nobody reads a pipe while they wait
        )  # fmt: skip
        for core in ("A", "B")
    ]
    evals = tmp_path / "results" / "temporal_evals"
    names = [f"{m}_s{s}" for m in ("u4d_most", "u4d_no_temporal", "baseline_most") for s in (0, 1)]
    names += [f"fusion_{v}_s0" for v in ("cascade", "add", "concat")]
    deadline = time.monotonic() + 150
    while not all((evals / n / "budget.json").is_file() for n in names) and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)
    assert all((evals / n / "budget.json").is_file() for n in names)  # the ended queues' tasks were taken over
    assert not (evals / "floor").exists() and all(p.poll() is None for p in procs)  # both wait for the live holder
    (claims / "floor").unlink()  # the holder ended without scoring it: a queue takes it over
    for proc, core in zip(procs, ("A", "B")):
        assert proc.wait(timeout=60) == 0, (tmp_path / f"queue_{core}.err").read_text()[-3000:]
    assert (evals / "floor" / "evaluation.json").is_file() and (tmp_path / "results" / "temporal.json").is_file()


def test_one_net_mode_fine_tunes_one_u4d_net_on_its_sources_loss_at_the_baselines_budget(queue_env, tmp_path):
    recipe = ("diffusion.min_snr_gamma=null", "diffusion.cond_noise=0.05")  # the final single-frame recipe's
    sources = {
        "u4d": save_checkpoint(tmp_path / "u4d.pt", TINY, ("diffusion.stage=u4d", *recipe)),
        "baseline": save_checkpoint(tmp_path / "baseline.pt", TINY, ("diffusion.min_snr_gamma=null",)),
    }
    env = {**queue_env, "ONE_NET": "1", "SOURCE_U4D": str(sources["u4d"]), "SOURCE_BASELINE": str(sources["baseline"])}
    run_both(SCRIPT, REPO, env)
    made = recorded_calls(tmp_path)
    runs, results = tmp_path / "runs" / "temporal_one_net", tmp_path / "results"
    windows: dict[str, int] = {}
    for argv in made:
        args, cfg = check_call(argv, REPO)
        if argv[0] == "train-diffusion":
            stage = cfg.diffusion.stage
            assert stage in ("u4d", "baseline") and cfg.init_from == str(sources[stage]) and cfg.frames == 4
            assert cfg.diffusion.min_snr_gamma is None and cfg.diffusion.cond_noise == (0.05 if stage == "u4d" else 0)
            windows[str(args.out)] = cfg.steps * cfg.batch_size
        elif argv[0] == "generate":
            assert cfg.mode == "u4d" or cfg.baseline.startswith(str(runs / "baseline_most_s"))
            if cfg.mode == "u4d":  # the one net for both stages
                assert (cfg.stage1, cfg.stage2) == ("", "") and Path(cfg.net).parent.parent == runs
                assert Path(cfg.net).name == "u4d"
        elif argv[0] == "evaluate":
            assert args.out.parent in (results / "temporal_evals_one_net", results / "temporal_evals")  # + the floor
    nets = [runs / f"{m}_s{s}" / "u4d" for m in ("u4d_most", "u4d_no_temporal") for s in (0, 1)]
    nets += [runs / f"baseline_most_s{s}" for s in (0, 1)]
    assert sorted(windows) == sorted(map(str, nets))
    assert set(windows.values()) == {40}  # one net: 20 steps x 2 windows (one per task) = the baseline's 40 x 1
    no_temporal = [a for a in made if a[0] == "train-diffusion" and "u4d_no_temporal" in option(a, "--out")]
    assert len(no_temporal) == 2 and all("net.most=false" in a for a in no_temporal)
    gates = [(a[1], option(a, "--role"), option(a, "--png")) for a in made if a[0] == "gates"]
    assert gates == [
        (f"{runs}/u4d_most_s0/u4d", "stage2", f"{results}/most_gates_one_net.png"),
        (f"{runs}/u4d_most_s0/u4d", "stage1", f"{results}/most_gates_one_net_stage1.png"),
    ]
    budget = json.loads((results / "temporal_evals_one_net" / "u4d_most_s1" / "budget.json").read_text())
    assert budget["nets"] == {"u4d": {"steps": 20, "minutes": 20.0}}
    table = json.loads((results / "temporal_one_net.json").read_text())
    assert set(table["methods"]) == {"u4d_most", "baseline_most", "u4d_no_temporal", "floor"} and table["fusion"] == {}
    assert table["methods"]["u4d_most"]["nets"] == [{"u4d": {"steps": 20, "minutes": 20.0}}] * 2
    assert not (results / "temporal.json").exists()  # the two-net table is not touched

    (tmp_path / "calls.jsonl").unlink()
    run_both(SCRIPT, REPO, {**env, "PROPAGATE": "1"})  # the same nets, propagated: its own evaluations and table
    made = recorded_calls(tmp_path)
    assert not [a for a in made if a[0] == "train-diffusion"]
    generated = [a for a in made if a[0] == "generate"]
    assert len(generated) == 6 and all(check_call(a, REPO)[1].propagate for a in generated)
    scored = {Path(option(a, "--out")).parent for a in made if a[0] == "evaluate"}
    assert scored == {results / "temporal_evals_one_net_propagated"}
    assert json.loads((results / "temporal_one_net_propagated.json").read_text())["methods"]["u4d_most"]["seeds"] == 2
