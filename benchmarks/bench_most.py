"""Cost of MoST: an L-frame sequence through a MoST net vs L single frames through the same net, L = 1, 2, 4.

    python benchmarks/bench_most.py                        # configs/u4d/cpu_hdl64.yaml (64x1024) with net.most=true
    python benchmarks/bench_most.py --quick --out /tmp/most.json   # configs/u4d/tiny_most.yaml (16x64), seconds

The net is the preset's baseline UNet with MoST blocks (`net.most=true`, untrained: the cost does not depend on the
weights), in eval mode without gradients. `sequence`: one (1, L, C, H, W) input, the MoST blocks mix the L frames
(temporal convolution and gates over them). `frames`: the same L frames as a batch (L, C, H, W) of single scans
through the same net, each frame its own length-1 sequence (no temporal mixing). `plain`: the L single frames
through the preset's net without MoST blocks (`net.most=false`), the reference a sequence model is compared with.
Timed: seconds per forward and per sampled sequence (`generate_baseline`, `--sampler` at `--steps`; L samples of
one frame for `frames` and `plain`, one generator each as in `u4d generate`). Each repetition times every L and
variant before the next starts (interleaved, so load from other processes hits all alike); medians over `--reps`.
Writes benchmarks/results/speed/most_cost.json and a .md beside it (--quick: the temp folder); `--out` redirects.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

from u4d_aug.config import load_config
from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text
from u4d_aug.pipeline import Loaded, generate_baseline
from u4d_aug.sampling_settings import SamplingSettings
from u4d_aug.train import DiffusionTrainConfig, build_net

REPO = Path(__file__).resolve().parents[1]
PRESET = REPO / "configs" / "u4d" / "cpu_hdl64.yaml"
QUICK_PRESET = REPO / "configs" / "u4d" / "tiny_most.yaml"
VARIANTS = ("sequence", "frames", "plain")


def build(config: Path, most: bool) -> Loaded:
    """The preset's untrained baseline net (with or without MoST blocks) in eval mode, and its config."""
    cfg = load_config(DiffusionTrainConfig, config, ["diffusion.stage=baseline", f"net.most={str(most).lower()}"])
    torch.manual_seed(0)
    return build_net(cfg, "cpu").eval(), cfg


def forward_call(loaded: Loaded, frames: int, variant: str) -> Callable[[], object]:
    """One no-grad forward of an L-frame sequence (1, L, C, H, W) or of L single frames (L, C, H, W)."""
    net, cfg = loaded
    image = (cfg.net.in_channels, cfg.height, cfg.width)
    if variant == "sequence":
        x_t, log_snr = torch.randn(1, frames, *image), torch.zeros(1)
    elif variant in ("frames", "plain"):
        x_t, log_snr = torch.randn(frames, *image), torch.zeros(frames)
    else:
        raise ValueError(f"variant {variant!r} is not one of {VARIANTS}")
    return lambda: net(x_t, log_snr)


def sample_call(loaded: Loaded, frames: int, variant: str, steps: int, sampler: str) -> Callable[[], object]:
    """One sampled L-frame sequence, or L sampled single frames (one generator per sample)."""
    # the sampler alone: every step from the net's own x̂0 (no mean start)
    settings = SamplingSettings(sampler=sampler, steps=steps, stage1_steps=None, mean_start_below=None)
    if variant == "sequence":
        return lambda: generate_baseline(loaded, 1, torch.Generator().manual_seed(0), settings, frames)
    if variant in ("frames", "plain"):
        return lambda: generate_baseline(
            loaded, frames, [torch.Generator().manual_seed(i) for i in range(frames)], settings, 1
        )
    raise ValueError(f"variant {variant!r} is not one of {VARIANTS}")


def seconds(call: Callable[[], object]) -> float:
    """Wall time of one call without gradients."""
    with torch.no_grad():
        start = time.perf_counter()
        call()
        return time.perf_counter() - start


def time_all(nets: dict[str, Loaded], frames: list[int], reps: int, steps: int, sampler: str) -> dict:
    """{L: {variant: {forward_s, sample_s}}} medians of `reps` interleaved repetitions (one warm-up first)."""
    calls = {}
    for length in frames:
        for variant in VARIANTS:
            loaded = nets["plain" if variant == "plain" else "most"]
            calls[(length, variant, "forward_s")] = forward_call(loaded, length, variant)
            if steps > 0:
                calls[(length, variant, "sample_s")] = sample_call(loaded, length, variant, steps, sampler)
    for call in calls.values():  # warm-up: allocator and oneDNN kernels
        seconds(call)
    times: dict[tuple, list[float]] = {key: [] for key in calls}
    for _ in range(reps):
        for key, call in calls.items():
            times[key].append(seconds(call))
    table: dict = {}
    for (length, variant, name), values in times.items():
        table.setdefault(str(length), {}).setdefault(variant, {})[name] = statistics.median(values)
        table[str(length)][variant][name + "_reps"] = values
    for length in table.values():
        for name in ("forward_s", "sample_s"):
            if name in length["sequence"]:
                length[f"{name.removesuffix('_s')}_ratio_sequence_vs_frames"] = (
                    length["sequence"][name] / length["frames"][name]
                )
                length[f"{name.removesuffix('_s')}_ratio_sequence_vs_plain"] = (
                    length["sequence"][name] / length["plain"][name]
                )
    return table


def markdown(result: dict) -> str:
    """The result as a markdown table."""
    lines = [
        f"# MoST cost: L-frame sequence vs L single frames ({result['height']}x{result['width']}, "
        f"{result['sampler']} {result['steps']} steps, medians of {result['reps']} reps)",
        "",
        f"Params: MoST net {result['params']['most']:,}, plain net {result['params']['plain']:,}. "
        f"Threads {result['threads']}; load {result['load_average_before']} -> {result['load_average_after']}.",
        "",
        "| L | forward seq (s) | forward L frames (s) | forward L plain (s) | seq / frames | seq / plain "
        "| sample seq (s) | sample L frames (s) | sample L plain (s) | seq / frames | seq / plain |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for length, row in result["frames"].items():
        cells = [length]
        for name in ("forward", "sample"):
            key = f"{name}_s"
            if key not in row["sequence"]:
                cells += ["-"] * 5
                continue
            cells += [f"{row[v][key]:.4f}" for v in VARIANTS]
            cells += [f"{row[f'{name}_ratio_sequence_vs_frames']:.2f}", f"{row[f'{name}_ratio_sequence_vs_plain']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"Command: `{result['command']}`", ""]
    return "\n".join(lines)


def default_out(quick: bool) -> Path:
    """benchmarks/results/speed/most_cost.json; --quick: the temp folder (never over the real result)."""
    if quick:
        return Path(tempfile.gettempdir()) / "most_cost_quick.json"
    return REPO / "benchmarks" / "results" / "speed" / "most_cost.json"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """Command line, with the defaults of the full run or of --quick."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=None, help="preset (default cpu_hdl64; quick tiny_most)")
    parser.add_argument("--frames", type=int, nargs="+", default=[1, 2, 4], help="sequence lengths L")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions (5; quick 3)")
    parser.add_argument("--steps", type=int, default=None, help="sampling steps, 0 skips sampling (8; quick 2)")
    parser.add_argument("--sampler", default="ddim", choices=["ddpm", "ddim", "dpmpp2m", "dpmpp2m-sde"])
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--quick", action="store_true", help="tiny_most preset (16x64), 2 steps, 3 reps")
    parser.add_argument("--out", type=Path, default=None, help="json path (.md beside it)")
    args = parser.parse_args(argv)
    args.config = args.config or (QUICK_PRESET if args.quick else PRESET)
    args.reps = args.reps if args.reps is not None else (3 if args.quick else 5)
    args.steps = args.steps if args.steps is not None else (2 if args.quick else 8)
    if args.reps < 1 or args.steps < 0 or min(args.frames) < 1:
        parser.error("--reps >= 1, --steps >= 0 and --frames >= 1 expected")
    return args


def main(argv: list[str] | None = None) -> int:
    """Time, print the table, write the json and the .md."""
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    try:
        nets = {"most": build(args.config, True), "plain": build(args.config, False)}
        table = time_all(nets, args.frames, args.reps, args.steps, args.sampler)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    _, cfg = nets["most"]
    result = {
        "benchmark": "most_cost",
        "command": " ".join(["python", "benchmarks/bench_most.py", *(sys.argv[1:] if argv is None else argv)]),
        "machine": host_info(),
        "threads": torch.get_num_threads(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "quick": args.quick,
        "config": str(args.config.relative_to(REPO) if args.config.is_relative_to(REPO) else args.config),
        "height": cfg.height,
        "width": cfg.width,
        "sampler": args.sampler,
        "steps": args.steps,
        "reps": args.reps,
        "params": {name: sum(p.numel() for p in net.parameters()) for name, (net, _) in nets.items()},
        "frames": table,
    }
    report = markdown(result)
    print("\n" + report)
    out = args.out or default_out(args.quick)
    atomic_write_json(out, result)
    atomic_write_text(out.with_suffix(".md"), report)
    print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
