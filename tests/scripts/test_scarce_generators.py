"""scripts/scarce_generators.sh run end to end with the stand-in `u4d` (tests/scripts/stand_in.py): the segmentor's
probabilities and both generators cover exactly the data-scarce setting's 18 places (read from the segmentor's run
folder), the banks come from the last milestone, a rerun starts nothing, and a missing segmentor is a clear error."""

from __future__ import annotations

import json
import subprocess

import yaml

from tests.scripts.stand_in import check_call, recorded_calls, stand_in_env
from tests.tiny_nets import REPO

SCRIPT = REPO / "scripts" / "scarce_generators.sh"
LABELLED = ["05", "11"]
POOL = ["01", "68"]


def segmentor_folder(tmp_path):
    """A sup-only run folder of the scarce setting: model, its split (labelled places) and config (the pool)."""
    folder = tmp_path / "seg"
    (folder / "splits").mkdir(parents=True)
    (folder / "model.pt").write_bytes(b"")
    split = {"labeled": [[s, "000000"] for s in LABELLED], "unlabeled": [["01", "000000"], ["40", "000000"]]}
    (folder / "splits" / "sequence_10pct_seed0_x.json").write_text(json.dumps(split))
    (folder / "config.yaml").write_text(yaml.safe_dump({"data": {"unlabeled_sequences": POOL}}))
    return folder


def run_script(env):
    return subprocess.run(["bash", str(SCRIPT)], cwd=REPO, env=env, capture_output=True, text=True, timeout=180)


def test_probabilities_nets_and_banks_cover_the_scarce_places_only(tmp_path):
    runs = tmp_path / "runs"
    segmentor = str(segmentor_folder(tmp_path) / "model.pt")
    env = stand_in_env(tmp_path, RUNS=str(runs), STEPS="2", SEGMENT="2", NUM="8", DATA=str(tmp_path / "data"),
                       BANKS=str(tmp_path / "banks"), SEGMENTOR=segmentor)  # fmt: skip
    done = run_script(env)
    assert done.returncode == 0, done.stderr[-3000:]
    places = sorted(LABELLED + POOL)
    calls = recorded_calls(tmp_path)
    predicted = [argv for argv in calls if argv[0] == "seg-predict"]
    assert len(predicted) == 1
    args, _ = check_call(predicted[0], REPO)
    assert args.sequences == places and args.out == tmp_path / "data" / "scarce_probs"
    trained, banks = [], {}
    for argv in calls:
        if argv[0] == "train-diffusion":
            _, cfg = check_call(argv, REPO)
            assert cfg.sequences == places and cfg.probs_root == str(tmp_path / "data" / "scarce_probs")
            trained.append((cfg.diffusion.stage, cfg.steps))
        elif argv[0] == "generate":
            args, cfg = check_call(argv, REPO)
            if cfg.num == 8:
                banks[args.out.name] = cfg.baseline if cfg.mode == "baseline" else cfg.net
    assert trained == [("u4d", 2), ("baseline", 2)]
    assert banks == {
        "scarce_u4d_hdl64": str(runs / "scarce" / "u4d_milestones" / "step_2.pt"),
        "scarce_r2dm_hdl64": str(runs / "scarce" / "baseline_milestones" / "step_2.pt"),
    }
    assert run_script(env).returncode == 0
    assert recorded_calls(tmp_path) == calls  # everything there: no call


def test_the_cascade_recipe_reaches_the_layout_nets_and_every_bank(tmp_path):
    runs = tmp_path / "runs"
    segmentor = str(segmentor_folder(tmp_path) / "model.pt")
    env = stand_in_env(tmp_path, RUNS=str(runs), STEPS="2", SEGMENT="2", NUM="8", DATA=str(tmp_path / "data"),
                       BANKS=str(tmp_path / "banks"), SEGMENTOR=segmentor, DETAIL="nearest",
                       LAYOUT="height=64 width=256 crop_width=0")  # fmt: skip
    done = run_script(env)
    assert done.returncode == 0, done.stderr[-3000:]
    generated = 0
    for argv in recorded_calls(tmp_path):
        if argv[0] == "train-diffusion":
            _, cfg = check_call(argv, REPO)
            assert (cfg.height, cfg.width, cfg.crop_width) == (64, 256, 0) and cfg.sequences == sorted(LABELLED + POOL)
        elif argv[0] == "generate":
            _, cfg = check_call(argv, REPO)
            assert cfg.detail == "nearest"  # the milestones' banks and the two final banks alike
            generated += 1
    assert generated == 4


def test_a_missing_segmentor_says_how_to_train_it(tmp_path):
    env = stand_in_env(tmp_path, RUNS=str(tmp_path / "runs"), SEGMENTOR=str(tmp_path / "none.pt"))
    done = run_script(env)
    assert done.returncode == 2 and "none.pt not found" in done.stderr and "--arms sup-only" in done.stderr
    assert recorded_calls(tmp_path) == []
