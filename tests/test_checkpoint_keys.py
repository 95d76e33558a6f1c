"""Checkpoints and weights files that load safely but hold a missing or ill-typed key (config, optimizer,
ema, model, step, rng, class_names, trained) give one `error:` line and exit 2 in every loader, never a traceback.

Each case replaces one key of a genuine file by a junk value (or drops it) and runs the commands that read it.
"""

from __future__ import annotations

import copy
import traceback
from pathlib import Path

import pytest
import torch

from tests.tiny_nets import SEG_TINY, TINY, save_checkpoint
from tests.tiny_worlds import write_toy_root
from u4d_aug.cli import main
from u4d_aug.export_weights import export_weights

JUNK = {"missing": None, "text": "x", "list": [1], "mapping": {"a": 1}}


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("keys")
    root = write_toy_root(base / "root", frames=2)
    ckpt = save_checkpoint(base / "diffusion.pt", TINY, ("diffusion.stage=baseline", f"data_root={root}"), step=3)
    export_weights(ckpt, base / "weights.pt", data_root="nowhere")
    assert main(["seg-train", str(SEG_TINY), f"data.root={root}", "optim.steps=1", "eval_every=1",
                 "--out", str(base / "seg"), "--no-progress", "--quiet"]) == 0  # fmt: skip
    return {
        "base": base,
        "root": root,
        "diffusion": ckpt,
        "weights": base / "weights.pt",
        "seg": base / "seg" / "model.pt",
    }


def commands(kind: str, path: Path, files: dict, out: Path) -> list[list[str]]:
    """The commands that read a file of `kind`."""
    root = str(files["root"])
    if kind == "seg":
        return [["seg-eval", str(path), root, "--no-progress"],
                ["seg-predict", str(path), root, "--out", str(out / "p"), "--no-progress"]]  # fmt: skip
    generate = ["generate", "configs/u4d/generate_cpu.yaml", "mode=baseline", f"baseline={path}", "num=1", "steps=1",
                "--no-progress", "--out", str(out / "g")]  # fmt: skip
    init = ["train-diffusion", str(TINY), f"data_root={root}", "steps=1", "--no-progress", "--out", str(out / "i"),
            f"init_from={path}"]  # fmt: skip
    if kind == "weights":
        return [generate, init]
    resume = ["train-diffusion", str(TINY), f"data_root={root}", "steps=4", "--no-progress", "--out", str(out / "r"),
              "--resume", str(path)]  # fmt: skip
    return [generate, init, resume, ["export-weights", str(path), "--out", str(out / "w.pt")]]


CASES = [("diffusion", key, junk) for key in ("config", "optimizer", "ema", "model", "step", "rng") for junk in JUNK]
CASES += [("weights", key, junk) for key in ("config", "model", "weights_hash") for junk in ("missing", "mapping")]
CASES += [("seg", key, junk) for key in ("class_names", "config", "model") for junk in ("text", "mapping")]


@pytest.mark.parametrize(("kind", "key", "junk"), CASES, ids=[f"{k}-{key}-{j}" for k, key, j in CASES])
def test_an_ill_typed_key_is_one_line_in_every_loader(files, tmp_path, capsys, monkeypatch, kind, key, junk):
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    state = copy.deepcopy(torch.load(files[kind], weights_only=True))
    if junk == "missing":
        state.pop(key, None)
    else:
        state[key] = JUNK[junk]
    path = tmp_path / f"{kind}_{key}_{junk}.pt"
    torch.save(state, path)
    refused = []
    for argv in commands(kind, path, files, tmp_path):
        try:
            code = main(argv)
        except BaseException:  # noqa: BLE001 - the point is that nothing escapes
            pytest.fail(f"{argv[0]}: traceback\n{traceback.format_exc()}")
        err = capsys.readouterr().err
        if code != 0:  # some keys are optional (a resume without rng state starts its RNG afresh)
            errors = [line for line in err.splitlines() if line.startswith("error: ")]
            assert code == 2 and len(errors) == 1 and "Traceback" not in err, (argv[0], err)
            refused.append(argv[0])
    assert refused, f"no command refused {kind} with {key} {junk}"  # every key here is required by some reader
