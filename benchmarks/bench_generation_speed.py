"""Generation and training speed of U4D (stage 1 + stage 2) vs the R2DM-style baseline, and the UNet's GFLOP/s.

    python benchmarks/bench_generation_speed.py            # configs/u4d/cpu.yaml, DDPM 32 steps (stage 1: 16)
    python benchmarks/bench_generation_speed.py --quick    # configs/u4d/tiny.yaml, DDPM 4 steps (stage 1: 2)
    python benchmarks/bench_generation_speed.py --stage1-overrides net.base_channels=8 --stage1-steps 8
    python benchmarks/bench_generation_speed.py --stage1 runs/u4d_cpu_stage1 --stage2 runs/u4d_cpu_stage2 \
        --baseline runs/u4d_cpu_baseline             # trained nets (EMA weights) instead of preset-built ones

Nets: built from the preset (`u4d_aug.train.build_net`, untrained weights: the cost does not depend on them),
with `--stage1-overrides key=value ..` applied to stage 1 only, or loaded from checkpoints
(`u4d_aug.pipeline.load_generator`). All nets must share one resolution.
Generation: seconds per scan of `generate_u4d` (stage 1 with `--stage1-steps`, then stage 2 with `--steps`)
and of `generate_baseline` (`--steps`), with `--sampler` (DDPM, as `u4d generate`; DDIM costs the same per step),
at each `--batches` size (per-scan = call time / batch, one generator per scan as in `u4d generate`);
stage 1 alone (`generate_stage1`) is timed too, stage 2 = U4D - stage 1. Repetitions interleave U4D and
the baseline so that load from other processes hits both alike. Two ratios: of the medians, and the median of
the per-repetition ratios (each U4D call over the baseline call right after it: load that drifts between
repetitions cancels); the goal U4D <= 1.3x is judged on the paired one, the worst over batch sizes.
Training: one step = GaussianDiffusion forward (losses) + backward + grad-norm clip + AdamW + EMA, as in
`u4d_aug.train.train`, at the preset's batch size on synthetic range images (x0 uniform in [-1, 1], m_u
Bernoulli(uncertainty.k) when k is a fraction, else 0.1, x0_u = x0 on m_u and -1 elsewhere; `stage_inputs`).
FLOPs: `torch.utils.flop_counter.FlopCounterMode` counts matmul/conv/attention FLOPs (not norms or
elementwise ops); achieved GFLOP/s = FLOPs of one no-grad forward / its median time, against a square float32
matmul timed in the same run with the same threads. Goal: UNet >= 50% of the matmul, judged on the baseline
net (the preset's UNet; a lighter stage 1 is expected to fall short) at the largest batch, and on a one-scan
forward of the full-size preset's UNet (paper widths, 64x1024; `--full-reps`; against the faster of two
2048² matmul runs around it). Params and GFLOP per forward (one scan) are also given at 64x1024 and for the full-size
preset, counted on the meta device.
Writes benchmarks/results/generation_speed.json. On a shared machine, compare ratios rather than absolutes;
the 1/5/15-min load averages before and after are recorded.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

from u4d_aug.config import load_config
from u4d_aug.diffusion import GaussianDiffusion
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json
from u4d_aug.pipeline import Loaded, generate_baseline, generate_stage1, generate_u4d, load_generator
from u4d_aug.train import DiffusionTrainConfig, build_net, stage_inputs

REPO = Path(__file__).resolve().parents[1]
STAGES = ("stage1", "stage2", "baseline")
FULL_PRESET = REPO / "configs" / "u4d" / "full_hdl64.yaml"
GOAL_RATIO = 1.3
GOAL_FRACTION = 0.5


def seconds_per_call(function: Callable[[], object], calls: int = 1) -> float:
    """Seconds per call of `function` over `calls` calls."""
    start = time.perf_counter()
    for _ in range(calls):
        function()
    return (time.perf_counter() - start) / calls


def shown(path: Path | None) -> str | None:
    """`path` relative to the repository when inside it (for the table and the json)."""
    if path is None:
        return None
    resolved = Path(path).resolve()
    return str(resolved.relative_to(REPO)) if resolved.is_relative_to(REPO) else str(path)


def preset_config(path: Path, stage: str, overrides: list[str]) -> DiffusionTrainConfig:
    return load_config(DiffusionTrainConfig, path, [f"diffusion.stage={stage}", *overrides])


def load_nets(args: argparse.Namespace) -> dict[str, Loaded]:
    """stage -> (net in eval mode without grads, its config): from a checkpoint if given, else from the preset."""
    nets = {}
    for stage in STAGES:
        ckpt = getattr(args, stage)
        if ckpt is not None:
            net, cfg = load_generator(ckpt)
            if cfg.diffusion.stage != stage:
                raise InputError(f"--{stage} {ckpt}: is a {cfg.diffusion.stage} checkpoint")
        else:
            cfg = preset_config(args.config, stage, args.stage1_overrides if stage == "stage1" else [])
            net = build_net(cfg).requires_grad_(False).eval()
        nets[stage] = (net, cfg)
    sizes = {stage: (cfg.height, cfg.width) for stage, (_, cfg) in nets.items()}
    if len(set(sizes.values())) != 1:
        raise InputError(f"the nets must share one resolution, got {sizes}")
    return nets


def time_generation(nets: dict[str, Loaded], args: argparse.Namespace) -> list[dict]:
    """Per-scan seconds of U4D, its stage 1 and the baseline at each batch size; reps interleave the three."""
    stage1, stage2, baseline = nets["stage1"], nets["stage2"], nets["baseline"]
    tasks = {}
    for batch in args.batches:
        tasks[(batch, "u4d")] = functools.partial(
            generate_u4d, stage1, stage2, batch, args.steps, sampler=args.sampler, stage1_steps=args.stage1_steps
        )
        tasks[(batch, "stage1")] = functools.partial(
            generate_stage1, stage1, batch, args.stage1_steps, sampler=args.sampler
        )
        tasks[(batch, "baseline")] = functools.partial(
            generate_baseline, baseline, batch, args.steps, sampler=args.sampler
        )
    for (batch, _), function in tasks.items():  # warm-up
        function(generator=[torch.Generator().manual_seed(i) for i in range(batch)])
    seconds: dict[tuple, list[float]] = {key: [] for key in tasks}
    for rep in range(args.reps):
        for (batch, name), function in tasks.items():
            generators = [torch.Generator().manual_seed(rep * 1000 + i) for i in range(batch)]  # one per scan
            start = time.perf_counter()
            function(generator=generators)
            seconds[(batch, name)].append((time.perf_counter() - start) / batch)
        print(f"  generation rep {rep + 1}/{args.reps}", flush=True)
    rows = []
    for batch in args.batches:
        u4d, first, base = (statistics.median(seconds[(batch, name)]) for name in ("u4d", "stage1", "baseline"))
        paired = [u / b for u, b in zip(seconds[(batch, "u4d")], seconds[(batch, "baseline")], strict=True)]
        rows.append(
            {
                "batch": batch,
                "u4d_s_per_scan": u4d,
                "stage1_s_per_scan": first,
                "stage2_s_per_scan": u4d - first,
                "baseline_s_per_scan": base,
                "u4d_over_baseline": u4d / base,
                "u4d_over_baseline_paired": statistics.median(paired),
                "u4d_over_baseline_reps": paired,
                "u4d_s_per_scan_reps": seconds[(batch, "u4d")],
                "baseline_s_per_scan_reps": seconds[(batch, "baseline")],
            }
        )
    return rows


def synthetic_batch(cfg: DiffusionTrainConfig, generator: torch.Generator) -> dict[str, Tensor]:
    """x0 (B, 2, H, W) uniform in [-1, 1]; m_u (B, 1, H, W) ~ Bernoulli(k); x0_u = x0 on m_u, -1 elsewhere."""
    shape = (cfg.batch_size, 2, cfg.height, cfg.width)
    k = cfg.uncertainty.k if isinstance(cfg.uncertainty.k, float) and 0 < cfg.uncertainty.k < 1 else 0.1
    x0 = torch.rand(shape, generator=generator) * 2 - 1
    m_u = (torch.rand((cfg.batch_size, 1, cfg.height, cfg.width), generator=generator) < k).float()
    x0_u = torch.where(m_u.bool(), x0, torch.full_like(x0, -1.0))
    return {"x0": x0, "x0_u": x0_u, "m_u": m_u}


class TrainStep:
    """One training step of a stage as in `u4d_aug.train.train`: losses, backward, clip, AdamW, EMA."""

    def __init__(self, cfg: DiffusionTrainConfig) -> None:
        self.cfg = cfg
        self.net = build_net(cfg).train()
        self.diffusion = GaussianDiffusion(self.net, cfg.diffusion)
        self.optimizer = torch.optim.AdamW(
            self.net.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas, weight_decay=cfg.optim.weight_decay
        )
        self.ema = EMA(self.net, cfg.ema_decay, cfg.ema_warmup_steps)
        generator = torch.Generator().manual_seed(cfg.seed)
        self.inputs = stage_inputs(cfg.diffusion.stage, synthetic_batch(cfg, generator))
        self.generator = torch.Generator().manual_seed(cfg.seed + 1)

    def __call__(self) -> None:
        x0, cond, m_u = self.inputs
        losses = self.diffusion(x0, cond, m_u, self.generator)
        self.optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        clip = self.cfg.optim.grad_clip if self.cfg.optim.grad_clip > 0 else float("inf")
        nn.utils.clip_grad_norm_(self.net.parameters(), clip)
        self.optimizer.step()
        self.ema.update(self.net)

    def count_flops(self) -> int:
        """FLOPs of the forward and backward of one step (optimizer and EMA not counted)."""
        x0, cond, m_u = self.inputs
        with FlopCounterMode(display=False) as counter:
            self.diffusion(x0, cond, m_u, self.generator)["loss"].backward()
        self.net.zero_grad(set_to_none=True)
        return counter.get_total_flops()


def time_training(nets: dict[str, Loaded], args: argparse.Namespace) -> list[dict]:
    """Steps/s of each stage at its config's batch size; reps interleave the stages."""
    steps = {stage: TrainStep(cfg) for stage, (_, cfg) in nets.items()}
    flops = {stage: step.count_flops() for stage, step in steps.items()}
    for step in steps.values():
        step()  # warm-up (and the first AdamW step allocates its state)
    seconds: dict[str, list[float]] = {stage: [] for stage in steps}
    for rep in range(args.train_steps):
        for stage, step in steps.items():
            seconds[stage].append(seconds_per_call(step))
        print(f"  training step {rep + 1}/{args.train_steps}", flush=True)
    rows = []
    for stage, step in steps.items():
        median = statistics.median(seconds[stage])
        rows.append(
            {
                "stage": stage,
                "batch_size": step.cfg.batch_size,
                "median_step_s": median,
                "steps_per_s": 1.0 / median,
                "gflop_per_step": flops[stage] / 1e9,
                "achieved_gflop_per_s": flops[stage] / 1e9 / median,
                "timed_steps": len(seconds[stage]),
            }
        )
    return rows


def net_inputs(net: nn.Module, batch: int, height: int, width: int, device: str = "cpu") -> tuple:
    """(x_t, log_snr, cond) of a forward of `net` on `batch` scans of height x width."""
    cfg = net.cfg
    x_t = torch.zeros(batch, cfg.in_channels, height, width, device=device)
    cond = torch.zeros(batch, cfg.cond_channels, height, width, device=device) if cfg.cond_channels else None
    return x_t, torch.zeros(batch, device=device), cond


def forward_flops(net: nn.Module, batch: int, height: int, width: int, device: str = "cpu") -> int:
    """FLOPs of one no-grad forward of `net` (on the meta device nothing is computed)."""
    inputs = net_inputs(net, batch, height, width, device)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        net(*inputs)
    return counter.get_total_flops()


def matmul_gflops(size: int, reps: int) -> dict:
    """GFLOP/s of a square float32 matmul (2 n³ FLOPs), median over repetitions after a warm-up."""
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(size, size, generator=generator)
    b = torch.randn(size, size, generator=generator)
    out = torch.empty(size, size)
    torch.mm(a, b, out=out)
    calls = max(1, 2 * 1024**3 // size**3)
    seconds = statistics.median(seconds_per_call(lambda: torch.mm(a, b, out=out), calls) for _ in range(reps))
    return {"size": size, "median_s": seconds, "gflop_per_s": 2 * size**3 / 1e9 / seconds}


def time_unet(nets: dict[str, Loaded], args: argparse.Namespace, matmul: float) -> list[dict]:
    """Achieved GFLOP/s of a no-grad forward of each net at each batch size, as a fraction of the matmul's."""
    tasks = {}
    for stage, (net, cfg) in nets.items():
        for batch in args.batches:
            inputs = net_inputs(net, batch, cfg.height, cfg.width)
            tasks[(stage, batch)] = (lambda n=net, i=inputs: n(*i), forward_flops(net, batch, cfg.height, cfg.width))
    with torch.no_grad():
        for function, _ in tasks.values():
            function()
        seconds: dict[tuple, list[float]] = {key: [] for key in tasks}
        for _ in range(args.reps):
            for key, (function, _) in tasks.items():
                seconds[key].append(seconds_per_call(function, args.forward_calls))
    rows = []
    for (stage, batch), (_, flops) in tasks.items():
        median = statistics.median(seconds[(stage, batch)])
        gflops = flops / 1e9 / median
        rows.append(
            {
                "stage": stage,
                "batch": batch,
                "gflop_per_forward": flops / 1e9,
                "median_forward_s": median,
                "gflop_per_s": gflops,
                "fraction_of_matmul": gflops / matmul,
            }
        )
    return rows


def time_full_unet(args: argparse.Namespace) -> dict | None:
    """Achieved GFLOP/s of a one-scan no-grad forward of the full-size preset's baseline UNet (paper widths,
    untrained: the cost does not depend on the weights) as a fraction of a 2048² matmul timed before and after
    it (the faster run: conservative); None when skipped."""
    if args.full_preset is None or args.full_reps < 1:
        return None
    matmul_before = matmul_gflops(2048, args.reps)["gflop_per_s"]
    cfg = preset_config(args.full_preset, "baseline", [])
    net = build_net(cfg).requires_grad_(False).eval()
    inputs = net_inputs(net, 1, cfg.height, cfg.width)
    flops = forward_flops(net, 1, cfg.height, cfg.width)
    with torch.no_grad():
        net(*inputs)  # warm-up
        median = statistics.median(seconds_per_call(lambda: net(*inputs)) for _ in range(args.full_reps))
    matmul = max(matmul_before, matmul_gflops(2048, args.reps)["gflop_per_s"])
    gflops = flops / 1e9 / median
    return {
        "source": shown(args.full_preset),
        "height": cfg.height,
        "width": cfg.width,
        "params": sum(p.numel() for p in net.parameters()),
        "batch": 1,
        "gflop_per_forward": flops / 1e9,
        "median_forward_s": median,
        "gflop_per_s": gflops,
        "matmul_gflop_per_s": matmul,
        "fraction_of_matmul": gflops / matmul,
        "reps": args.full_reps,
    }


def net_sizes(nets: dict[str, Loaded], args: argparse.Namespace) -> list[dict]:
    """Params and GFLOP of a one-scan forward: each net at its size and at 64x1024, the full preset at its size."""
    cases = []
    for stage, (_, cfg) in nets.items():
        source = shown(getattr(args, stage) or args.config)
        cases += [(stage, source, cfg, cfg.height, cfg.width), (stage, source, cfg, 64, 1024)]
    if args.full_preset is not None:
        for stage in STAGES:
            cfg = preset_config(args.full_preset, stage, [])
            cases.append((stage, shown(args.full_preset), cfg, cfg.height, cfg.width))
    rows = []
    for stage, source, cfg, height, width in cases:
        sized = dataclasses.replace(cfg, height=height, width=width, net=dataclasses.replace(cfg.net))
        net = build_net(sized).to("meta")
        rows.append(
            {
                "stage": stage,
                "source": source,
                "height": height,
                "width": width,
                "params": sum(p.numel() for p in net.parameters()),
                "gflop_per_forward": forward_flops(net, 1, height, width, "meta") / 1e9,
            }
        )
        del net
    return rows


def print_report(result: dict) -> None:
    print(
        f"\n{result['height']}x{result['width']}, {result['sampler'].upper()} {result['steps']} steps "
        f"(stage 1: {result['stage1_steps']}), "
        f"torch {result['torch']}, {result['threads']} threads, load average {result['load_average_before'][0]:.2f}"
        f" -> {result['load_average_after'][0]:.2f}"
    )
    header = (
        f"{'batch':>5} | {'U4D s/scan':>10} {'stage1':>8} {'stage2':>8} | {'baseline':>9} | "
        f"{'U4D/base':>8} {'paired':>7}"
    )
    print(header)
    print("-" * len(header))
    for row in result["generation"]:
        print(
            f"{row['batch']:>5} | {row['u4d_s_per_scan']:>10.4f} {row['stage1_s_per_scan']:>8.4f} "
            f"{row['stage2_s_per_scan']:>8.4f} | {row['baseline_s_per_scan']:>9.4f} | "
            f"{row['u4d_over_baseline']:>7.2f}x {row['u4d_over_baseline_paired']:>6.2f}x"
        )
    print(f"\n{'training':<9} {'batch':>5} {'steps/s':>8} {'step s':>8} {'GFLOP/step':>10} {'GFLOP/s':>8}")
    for row in result["training"]:
        print(
            f"{row['stage']:<9} {row['batch_size']:>5} {row['steps_per_s']:>8.3f} {row['median_step_s']:>8.4f} "
            f"{row['gflop_per_step']:>10.3f} {row['achieved_gflop_per_s']:>8.2f}"
        )
    mm = result["matmul"]
    print(f"\nmatmul {mm['size']}x{mm['size']} float32: {mm['gflop_per_s']:.2f} GFLOP/s")
    print(f"{'forward':<9} {'batch':>5} {'GFLOP':>8} {'s':>8} {'GFLOP/s':>8} {'of matmul':>9}")
    for row in result["unet"]:
        print(
            f"{row['stage']:<9} {row['batch']:>5} {row['gflop_per_forward']:>8.3f} {row['median_forward_s']:>8.4f} "
            f"{row['gflop_per_s']:>8.2f} {row['fraction_of_matmul']:>8.0%}"
        )
    full = result["unet_full"]
    if full is not None:
        print(
            f"{'full':<9} {full['batch']:>5} {full['gflop_per_forward']:>8.1f} {full['median_forward_s']:>8.3f} "
            f"{full['gflop_per_s']:>8.2f} {full['fraction_of_matmul']:>8.0%}  ({full['height']}x{full['width']}, "
            f"{full['params']:,} params, {full['source']})"
        )
    print(f"\n{'net':<9} {'H x W':>9} {'params':>11} {'GFLOP/scan':>10}  source")
    for row in result["nets"]:
        size = f"{row['height']}x{row['width']}"
        print(f"{row['stage']:<9} {size:>9} {row['params']:>11,} {row['gflop_per_forward']:>10.3f}  {row['source']}")
    goals = result["goals"]
    print(
        f"\ngoal U4D <= {GOAL_RATIO}x baseline per scan: {'met' if goals['u4d_ratio_met'] else 'NOT met'} "
        f"(worst over batch sizes of the paired median {goals['u4d_over_baseline_worst']:.2f}x)"
    )
    print(
        f"goal UNet >= {GOAL_FRACTION:.0%} of matmul: {'met' if goals['unet_fraction_met'] else 'NOT met'} "
        f"(baseline net at batch {goals['unet_fraction_batch']}: {goals['unet_fraction']:.0%})"
    )
    if goals["unet_full_fraction"] is not None:
        print(
            f"goal UNet >= {GOAL_FRACTION:.0%} of matmul, full-size preset: "
            f"{'met' if goals['unet_full_fraction_met'] else 'NOT met'} ({goals['unet_full_fraction']:.0%})"
        )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=None, help="preset (default configs/u4d/cpu.yaml)")
    parser.add_argument("--stage1", type=Path, default=None, help="stage-1 checkpoint or run folder")
    parser.add_argument("--stage2", type=Path, default=None, help="stage-2 checkpoint or run folder")
    parser.add_argument("--baseline", type=Path, default=None, help="baseline checkpoint or run folder")
    parser.add_argument(
        "--stage1-overrides", nargs="*", default=[], metavar="KEY=VALUE", help="applied to the stage-1 preset only"
    )
    parser.add_argument("--steps", type=int, default=None, help="sampling steps of stage 2 and the baseline (32)")
    parser.add_argument("--stage1-steps", type=int, default=None, help="sampling steps of stage 1 (16)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8], help="generation batch sizes")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions; medians are reported (5)")
    parser.add_argument("--train-steps", type=int, default=None, help="timed training steps per stage (5)")
    parser.add_argument("--forward-calls", type=int, default=3, help="UNet forwards per repetition")
    parser.add_argument("--matmul-size", type=int, default=None, help="square matmul size (2048)")
    parser.add_argument("--full-preset", type=Path, default=FULL_PRESET, help="preset counted for params/FLOPs")
    parser.add_argument("--full-reps", type=int, default=None, help="timed full-size forwards, 0 skips (3; quick 0)")
    parser.add_argument(
        "--sampler", choices=["ddpm", "ddim", "dpmpp2m"], default="ddpm", help="sampler of the timed generation"
    )
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    parser.add_argument("--quick", action="store_true", help="tiny preset, 4 (2) steps, 3 reps, matmul 512")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "generation_speed.json")
    args = parser.parse_args(argv)
    quick = args.quick
    defaults = {
        "config": REPO / "configs" / "u4d" / ("tiny.yaml" if quick else "cpu.yaml"),
        "steps": 4 if quick else 32,
        "stage1_steps": 2 if quick else 16,
        "reps": 3 if quick else 5,
        "train_steps": 3 if quick else 5,
        "matmul_size": 512 if quick else 2048,
        "full_reps": 0 if quick else 3,
    }
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.stage1_overrides and args.stage1 is not None:
        parser.error("--stage1-overrides applies to a preset-built stage 1, not to a --stage1 checkpoint")
    if min(args.steps, args.stage1_steps, args.reps, args.train_steps, args.forward_calls, *args.batches) < 1:
        parser.error("steps, stage1 steps, reps, train steps, forward calls and batches must be >= 1")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    try:
        nets = load_nets(args)
        print("generation ...", flush=True)
        generation = time_generation(nets, args)
        print("training ...", flush=True)
        training = time_training(nets, args)
        print("matmul and UNet forwards ...", flush=True)
        matmul = matmul_gflops(args.matmul_size, args.reps)
        unet = time_unet(nets, args, matmul["gflop_per_s"])
        print("full-size UNet forward ...", flush=True)
        full = time_full_unet(args)
        sizes = net_sizes(nets, args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    cfg = nets["baseline"][1]
    worst_ratio = max(row["u4d_over_baseline_paired"] for row in generation)
    largest = max(args.batches)
    fraction = next(r["fraction_of_matmul"] for r in unet if r["batch"] == largest and r["stage"] == "baseline")
    result = {
        "benchmark": "generation_speed",
        "command": " ".join(["python", "benchmarks/bench_generation_speed.py", *(argv or sys.argv[1:])]),
        "machine": host_info(),
        "threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(default)"),
        "load_average_before": list(load_before),
        "load_average_after": list(os.getloadavg()),
        "quick": args.quick,
        "config": shown(args.config),
        "stage1_overrides": args.stage1_overrides,
        "checkpoints": {stage: shown(getattr(args, stage)) for stage in STAGES},
        "height": cfg.height,
        "width": cfg.width,
        "sampler": args.sampler,
        "steps": args.steps,
        "stage1_steps": args.stage1_steps,
        "reps": args.reps,
        "generation": generation,
        "training": training,
        "matmul": matmul,
        "unet": unet,
        "unet_full": full,
        "nets": sizes,
        "goals": {
            "u4d_over_baseline_max": GOAL_RATIO,
            "u4d_over_baseline_worst": worst_ratio,
            "u4d_ratio_met": worst_ratio <= GOAL_RATIO,
            "unet_fraction_min": GOAL_FRACTION,
            "unet_fraction": fraction,
            "unet_fraction_net": "baseline",
            "unet_fraction_batch": largest,
            "unet_fraction_met": fraction >= GOAL_FRACTION,
            "unet_full_fraction": None if full is None else full["fraction_of_matmul"],
            "unet_full_fraction_met": None if full is None else full["fraction_of_matmul"] >= GOAL_FRACTION,
        },
    }
    print_report(result)
    atomic_write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
