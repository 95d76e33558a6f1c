"""scripts/latent_pilot.sh run end to end with the stand-in `u4d` (tests/scripts/stand_in.py): both methods on the
latent preset of one autoencoder, segment by segment at equal budgets, every call one the real commands accept, the
milestones scored with the autoencoder's row beside them, and a second run starts nothing."""

from __future__ import annotations

import subprocess
from pathlib import Path

from tests.scripts.stand_in import check_call, recorded_calls, stand_in_env
from tests.tiny_nets import REPO

SCRIPT = REPO / "scripts" / "latent_pilot.sh"


def run_pilot(env: dict) -> None:
    done = subprocess.run(["bash", str(SCRIPT)], cwd=REPO, env=env, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-3000:]


def test_both_methods_alternate_on_the_latent_preset_and_a_rerun_starts_nothing(tmp_path):
    ae = tmp_path / "ae" / "autoencoder.pt"
    ae.parent.mkdir()
    ae.write_bytes(b"")
    env = stand_in_env(tmp_path, RUNS=str(tmp_path / "runs"), AE=str(ae), NAME="p", METHOD="both", STEPS="4",
                       SEGMENT="2", EXTRA="net.base_channels=16")  # fmt: skip
    run_pilot(env)
    calls = recorded_calls(tmp_path)
    trained = []
    for argv in calls:
        if argv[0] == "py":
            assert argv[1] == "benchmarks/gates.py" and f"ae={ae}" in argv
            continue
        args, cfg = check_call(argv, REPO)
        if argv[0] == "train-diffusion":
            assert args.config == Path("configs/u4d/latent_hdl64.yaml") and cfg.autoencoder == str(ae)
            assert cfg.latent_factor == 4 and cfg.net.base_channels == 16
            trained.append((cfg.diffusion.stage, cfg.steps, args.out.name))
        elif argv[0] == "generate":
            assert cfg.num == 16 and (cfg.net or cfg.baseline).startswith(str(tmp_path / "runs" / "latent" / "p"))
        else:
            assert argv[0] == "export-weights", argv
    assert trained == [("u4d", 2, "u4d"), ("baseline", 2, "baseline"), ("u4d", 4, "u4d"), ("baseline", 4, "baseline")]
    gates = [argv for argv in calls if argv[0] == "py"]
    assert len(gates) == 4 and len([argv for argv in calls if argv[0] == "generate"]) == 4
    run_pilot(env)
    assert recorded_calls(tmp_path) == calls  # everything there: no call
