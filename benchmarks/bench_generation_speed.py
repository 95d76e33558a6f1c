"""Generation speed at the sensor's resolution (64x1024): U4D (stage 1 + stage 2) vs the R2DM-style baseline vs R2DM.

    python benchmarks/bench_generation_speed.py            # cpu_hdl64 preset, DPM-Solver++(2M) 20 steps (stage 1: 10)
                                                           # and DDPM 32 (16); anchor: full_hdl64 net x 256 steps
    python benchmarks/bench_generation_speed.py --quick --out /tmp/speed.json   # tiny preset, 4 (2) steps, < 30 s
    python benchmarks/bench_generation_speed.py --sampler ddim --steps 16 --stage1-steps 8 --compare-ddpm-steps 0
    python benchmarks/bench_generation_speed.py --stage1 runs/hdl64_stage1 --stage2 runs/hdl64_stage2 \
        --baseline runs/hdl64_baseline             # trained nets (EMA weights) instead of preset-built ones

Nets: a `--stage1/--stage2/--baseline` checkpoint or run folder if given (`--net`: one U4D net for both stages,
timed and sized once as "u4d"), else the shipped trained net when present: weights/u4d.pt (one net for both U4D
stages, also timed and sized once as "u4d"), weights/baseline.pt (`--weights DIR`, `--no-weights`; not used by
--quick), else built from the preset (`u4d_aug.train.build_net`, untrained: the cost does not depend
on the weights; `--stage1-overrides key=value ..` applies to a preset-built stage 1). All nets share one resolution.
Generation: seconds per scan of `generate_u4d` (stage 1 with `--stage1-steps`, then stage 2 with `--steps`), of
`generate_stage1` alone (stage 2 = U4D - stage 1) and of `generate_baseline` (`--steps`), with `--sampler` and, in
the same run, DDPM with `--compare-ddpm-steps` (stage 1: half), at each `--batches` size (per scan = call time /
batch, one generator per scan as in `u4d generate`). Every sampler/batch/net call of a repetition runs before the
next repetition starts, U4D then the baseline right after it, so that load from other processes hits both alike.
Two ratios: of the medians, and `paired` = the median of the per-repetition ratios (load that drifts between
repetitions cancels); the goal U4D <= 1.3x is judged on the paired one, the worst over batch sizes.
Anchor: R2DM's sampling cost = the median of `--anchor-reps` one-scan no-grad forwards of the R2DM-sized UNet
(`--anchor-preset`, configs/u4d/full_hdl64.yaml, untrained) at its 64x1024, each followed by a one-scan forward of
the baseline net, times R2DM's 256 DDPM steps (one forward per step; a timed 256-step run would take minutes).
Training: one step as in `u4d_aug.train.train` (losses on the preset's azimuth crops, backward, clip, AdamW, EMA)
at the preset's batch size on synthetic range images (`--train-steps`, 0 skips).
FLOPs: `torch.utils.flop_counter.FlopCounterMode` counts matmul/conv/attention FLOPs (not norms or elementwise
ops); achieved GFLOP/s = FLOPs / median time, of UNet forwards and of whole generations (steps x FLOPs per
forward), against a square float32 matmul timed in the same run with the same threads (for the anchor: the faster
of two 2048² matmul runs around it).
Writes benchmarks/results/speed/generation_speed_{H}x{W}.json (--quick: the temp folder; `--out` redirects) and a .md
with the tables beside it. On a shared machine, compare ratios rather than absolutes; load averages are recorded.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

from u4d_aug.batches import crop_batch, crop_offsets, stage_inputs
from u4d_aug.config import load_config
from u4d_aug.diffusion import STAGE2_TASK, GaussianDiffusion
from u4d_aug.ema import EMA
from u4d_aug.errors import InputError
from u4d_aug.host import host_info
from u4d_aug.io import atomic_write_json, atomic_write_text
from u4d_aug.pipeline import Loaded, generate_baseline, generate_stage1, generate_u4d, load_generator
from u4d_aug.sampling_settings import SamplingSettings
from u4d_aug.stage import DiffusionTrainConfig, build_net

REPO = Path(__file__).resolve().parents[1]
STAGES = ("stage1", "stage2", "baseline")
PRESET = REPO / "configs" / "u4d" / "cpu_hdl64.yaml"
QUICK_PRESET = REPO / "configs" / "u4d" / "tiny.yaml"
ANCHOR_PRESET = REPO / "configs" / "u4d" / "full_hdl64.yaml"
ANCHOR_STEPS = 256  # R2DM's DDPM sampling steps
WEIGHTS = REPO / "weights"
WEIGHT_FILES = {"stage1": "u4d.pt", "stage2": "u4d.pt", "baseline": "baseline.pt"}  # the shipped U4D: one net
# (steps, stage 1); dpmpp2m-sde: generate_hdl64.yaml's
DEFAULT_STEPS = {"ddpm": (32, 16), "ddim": (32, 16), "dpmpp2m": (20, 10), "dpmpp2m-sde": (20, 6)}
QUICK_STEPS = (4, 2)
GOAL_RATIO = 1.3
GOAL_FRACTION = 0.5


def seconds_per_call(function: Callable[[], object], calls: int = 1) -> float:
    """Seconds per call of `function` over `calls` calls."""
    start = time.perf_counter()
    for _ in range(calls):
        function()
    return (time.perf_counter() - start) / calls


def paired_ratio(numerators: list[float], denominators: list[float]) -> float:
    """Median of the per-repetition ratios numerator_i / denominator_i."""
    return statistics.median(n / d for n, d in zip(numerators, denominators, strict=True))


def shown(path: Path | None) -> str | None:
    """`path` relative to the repository when inside it (for the tables and the json)."""
    if path is None:
        return None
    resolved = Path(path).resolve()
    return str(resolved.relative_to(REPO)) if resolved.is_relative_to(REPO) else str(path)


def preset_config(path: Path, stage: str, overrides: list[str]) -> DiffusionTrainConfig:
    """The preset's training config for `stage`, with `overrides` applied."""
    return load_config(DiffusionTrainConfig, path, [f"diffusion.stage={stage}", *overrides])


def checkpoint_sources(args: argparse.Namespace) -> dict[str, Path | None]:
    """stage -> its --stage checkpoint, else the shipped weights file when present, else None (preset-built)."""
    sources: dict[str, Path | None] = {}
    for stage in STAGES:
        if args.net is not None and stage != "baseline":  # one net for both U4D stages
            sources[stage] = args.net
            continue
        shipped = None if args.weights is None else args.weights / WEIGHT_FILES[stage]
        overridden = stage == "stage1" and bool(args.stage1_overrides)
        if getattr(args, stage) is not None:
            sources[stage] = getattr(args, stage)
        elif shipped is not None and shipped.is_file() and not overridden:
            sources[stage] = shipped
        else:
            sources[stage] = None
    return sources


def load_nets(args: argparse.Namespace, sources: dict[str, Path | None]) -> dict[str, Loaded]:
    """stage -> (net in eval mode without grads, its config): from its checkpoint if any, else from the preset."""
    nets: dict[str, Loaded] = {}
    for stage, ckpt in sources.items():
        if ckpt is not None and stage == "stage2" and ckpt == sources["stage1"]:
            nets[stage] = nets["stage1"]  # a one-net U4D: the same net (object) serves both stages
            continue
        if ckpt is not None:
            net, cfg = load_generator(ckpt)
            one_net = cfg.diffusion.stage == "u4d" and stage in ("stage1", "stage2")
            if cfg.diffusion.stage != stage and not one_net:
                raise InputError(f"{ckpt}: is a {cfg.diffusion.stage} checkpoint, expected {stage}")
        else:
            cfg = preset_config(args.config, stage, args.stage1_overrides if stage == "stage1" else [])
            net = build_net(cfg).requires_grad_(False).eval()
        nets[stage] = (net, cfg)
    sizes = {stage: (cfg.height, cfg.width) for stage, (_, cfg) in nets.items()}
    if len(set(sizes.values())) != 1:
        raise InputError(f"the nets must share one resolution, got {sizes}")
    return nets


def distinct_nets(nets: dict[str, Loaded]) -> dict[str, Loaded]:
    """The nets to time and size once each: a one-net U4D (stage 1 and stage 2 the same net) as "u4d"."""
    if nets["stage1"] is nets["stage2"]:
        return {"u4d": nets["stage1"], "baseline": nets["baseline"]}
    return nets


def sampler_runs(args: argparse.Namespace) -> list[dict]:
    """The timed sampler configurations: `--sampler` first, then DDPM with `--compare-ddpm-steps` (if not the same)."""
    runs = [{"sampler": args.sampler, "steps": args.steps, "stage1_steps": args.stage1_steps}]
    if args.compare_ddpm_steps > 0:
        compare = {"sampler": "ddpm", "steps": args.compare_ddpm_steps, "stage1_steps": args.compare_stage1_steps}
        if compare != runs[0]:
            runs.append(compare)
    return runs


def net_inputs(net: nn.Module, batch: int, height: int, width: int, device: str = "cpu") -> tuple:
    """(x_t, log_snr, cond) of a forward of `net` on `batch` scans of height x width; a one-net U4D's forward also
    names its task (stage 2's: the condition is read by both tasks, so the cost is the same)."""
    cfg = net.cfg
    x_t = torch.zeros(batch, cfg.in_channels, height, width, device=device)
    cond = torch.zeros(batch, cfg.cond_channels, height, width, device=device) if cfg.cond_channels else None
    inputs = (x_t, torch.zeros(batch, device=device), cond)
    if cfg.num_tasks:  # RangeUNet.forward(x_t, log_snr, cond, generator, crop_offsets, poses, task)
        inputs = (*inputs, None, None, None, STAGE2_TASK)
    return inputs


def forward_flops(net: nn.Module, batch: int, height: int, width: int, device: str = "cpu") -> int:
    """FLOPs of one no-grad forward of `net` (on the meta device nothing is computed)."""
    inputs = net_inputs(net, batch, height, width, device)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        net(*inputs)
    return counter.get_total_flops()


def generation_tasks(nets: dict[str, Loaded], run: dict, batch: int) -> dict[str, Callable]:
    """name -> generation call at `batch` scans (U4D, then the baseline right after it, then stage 1 alone)."""
    stage1, stage2, baseline = nets["stage1"], nets["stage2"], nets["baseline"]
    # the samplers' cost alone: no mask cap, no mean start (preset-built nets store no training mean)
    settings = SamplingSettings(
        sampler=run["sampler"],
        steps=run["steps"],
        stage1_steps=run["stage1_steps"],
        stage1_mask_fraction=None,
        mean_start_below=None,
    )
    return {
        "u4d": functools.partial(generate_u4d, stage1, stage2, batch, settings=settings),
        "baseline": functools.partial(generate_baseline, baseline, batch, settings=settings),
        "stage1": functools.partial(generate_stage1, stage1, batch, settings=settings),
    }


def warm_up(nets: dict[str, Loaded], batches: list[int]) -> None:
    """One no-grad forward of each net at each batch size (allocator and kernels; a whole generation would be slow)."""
    with torch.no_grad():
        for net, cfg in nets.values():
            for batch in batches:
                net(*net_inputs(net, batch, cfg.height, cfg.width))


def generation_row(batch: int, seconds: dict[str, list[float]], gflop: dict[str, float], matmul: float) -> dict:
    """Medians, ratios, per-repetition times and achieved GFLOP/s of one sampler at one batch size."""
    u4d, first, base = (statistics.median(seconds[name]) for name in ("u4d", "stage1", "baseline"))
    return {
        "batch": batch,
        "u4d_s_per_scan": u4d,
        "stage1_s_per_scan": first,
        "stage2_s_per_scan": u4d - first,
        "baseline_s_per_scan": base,
        "u4d_over_baseline": u4d / base,
        "u4d_over_baseline_paired": paired_ratio(seconds["u4d"], seconds["baseline"]),
        "u4d_gflop_per_s": gflop["u4d"] / u4d,
        "baseline_gflop_per_s": gflop["baseline"] / base,
        "u4d_fraction_of_matmul": gflop["u4d"] / u4d / matmul,
        "baseline_fraction_of_matmul": gflop["baseline"] / base / matmul,
        "u4d_s_per_scan_reps": seconds["u4d"],
        "stage1_s_per_scan_reps": seconds["stage1"],
        "baseline_s_per_scan_reps": seconds["baseline"],
        "u4d_over_baseline_reps": [u / b for u, b in zip(seconds["u4d"], seconds["baseline"], strict=True)],
    }


def generation_gflop(run: dict, flops: dict[str, int]) -> dict[str, float]:
    """GFLOP per scan of each generation call: sampling steps x FLOPs of a one-scan forward (one forward a step)."""
    first = run["stage1_steps"] * flops["stage1"] / 1e9
    return {
        "stage1": first,
        "u4d": first + run["steps"] * flops["stage2"] / 1e9,
        "baseline": run["steps"] * flops["baseline"] / 1e9,
    }


def time_generation(
    nets: dict[str, Loaded], runs: list[dict], args: argparse.Namespace, flops: dict[str, int], matmul: float
) -> list[dict]:
    """Per sampler run: per-scan seconds of U4D, stage 1 and the baseline at each batch; reps interleave them all."""
    tasks = {
        (index, batch, name): function
        for index, run in enumerate(runs)
        for batch in args.batches
        for name, function in generation_tasks(nets, run, batch).items()
    }
    warm_up(nets, args.batches)
    seconds: dict[tuple, list[float]] = {key: [] for key in tasks}
    for rep in range(args.reps):
        for (index, batch, name), function in tasks.items():
            generators = [torch.Generator().manual_seed(rep * 1000 + i) for i in range(batch)]  # one per scan
            start = time.perf_counter()
            function(generator=generators)
            seconds[(index, batch, name)].append((time.perf_counter() - start) / batch)
        print(f"  generation rep {rep + 1}/{args.reps}", flush=True)
    out = []
    for index, run in enumerate(runs):
        gflop = generation_gflop(run, flops)
        rows = [
            generation_row(
                batch, {name: seconds[(index, batch, name)] for name in ("u4d", "stage1", "baseline")}, gflop, matmul
            )
            for batch in args.batches
        ]
        out.append({**run, "gflop_per_scan": gflop, "generation": rows})
    return out


def synthetic_batch(cfg: DiffusionTrainConfig, generator: torch.Generator) -> dict[str, Tensor]:
    """x0 (B, 2, H, W) uniform in [-1, 1]; m_u (B, 1, H, W) ~ Bernoulli(k); x0_u = x0 on m_u, -1 elsewhere."""
    shape = (cfg.batch_size, 2, cfg.height, cfg.width)
    k = cfg.uncertainty.k if isinstance(cfg.uncertainty.k, float) and 0 < cfg.uncertainty.k < 1 else 0.1
    x0 = torch.rand(shape, generator=generator) * 2 - 1
    m_u = (torch.rand((cfg.batch_size, 1, cfg.height, cfg.width), generator=generator) < k).float()
    x0_u = torch.where(m_u.bool(), x0, torch.full_like(x0, -1.0))
    return {"x0": x0, "x0_u": x0_u, "m_u": m_u}


class TrainStep:
    """One training step of a stage as in `u4d_aug.train.train`: crops, losses, backward, clip, AdamW, EMA."""

    def __init__(self, cfg: DiffusionTrainConfig) -> None:
        self.cfg = cfg
        self.net = build_net(cfg).train()
        self.diffusion = GaussianDiffusion(self.net, cfg.diffusion)
        self.optimizer = torch.optim.AdamW(
            self.net.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas, weight_decay=cfg.optim.weight_decay
        )
        self.ema = EMA(self.net, cfg.ema_decay, cfg.ema_warmup_steps)
        generator = torch.Generator().manual_seed(cfg.seed)
        batch = synthetic_batch(cfg, generator)
        self.offsets = crop_offsets(cfg.batch_size, cfg, generator)  # None: full panorama
        if self.offsets is not None:
            batch = crop_batch(batch, self.offsets, cfg.crop_width)
        self.inputs = stage_inputs(cfg.diffusion.stage, batch)
        self.generator = torch.Generator().manual_seed(cfg.seed + 1)

    def __call__(self) -> None:
        x0, cond, m_u = self.inputs
        losses = self.diffusion(x0, cond, m_u, self.generator, self.offsets)
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
            self.diffusion(x0, cond, m_u, self.generator, self.offsets)["loss"].backward()
        self.net.zero_grad(set_to_none=True)
        return counter.get_total_flops()


def time_training(nets: dict[str, Loaded], args: argparse.Namespace) -> list[dict]:
    """Steps/s of each stage at its config's batch size and crop width; reps interleave the stages."""
    if args.train_steps < 1:
        return []
    steps = {stage: TrainStep(cfg) for stage, (_, cfg) in distinct_nets(nets).items()}
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
                "width": step.cfg.crop_width or step.cfg.width,
                "median_step_s": median,
                "steps_per_s": 1.0 / median,
                "gflop_per_step": flops[stage] / 1e9,
                "achieved_gflop_per_s": flops[stage] / 1e9 / median,
                "timed_steps": len(seconds[stage]),
            }
        )
    return rows


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
    for stage, (net, cfg) in distinct_nets(nets).items():
        for batch in args.batches:
            inputs = net_inputs(net, batch, cfg.height, cfg.width)
            tasks[(stage, batch)] = (lambda n=net, i=inputs: n(*i), forward_flops(net, batch, cfg.height, cfg.width))
    warm_up(nets, args.batches)
    with torch.no_grad():
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


def time_anchor(nets: dict[str, Loaded], args: argparse.Namespace) -> dict | None:
    """R2DM's seconds per scan = median one-scan forward of the R2DM-sized UNet x 256 steps (None: skipped).

    Each anchor forward is followed by a one-scan forward of the baseline net (the paired ratio of the two);
    its GFLOP/s is a fraction of the faster of two 2048² matmul runs around it (conservative).
    """
    if args.anchor_reps < 1:
        return None
    matmul_before = matmul_gflops(2048, args.reps)["gflop_per_s"]
    cfg = preset_config(args.anchor_preset, "baseline", list(args.anchor_overrides))
    net = build_net(cfg).requires_grad_(False).eval()
    flops = forward_flops(net, 1, cfg.height, cfg.width)
    base, base_cfg = nets["baseline"]
    inputs = net_inputs(net, 1, cfg.height, cfg.width)
    base_inputs = net_inputs(base, 1, base_cfg.height, base_cfg.width)
    seconds: dict[str, list[float]] = {"anchor": [], "baseline": []}
    with torch.no_grad():
        net(*inputs)  # warm-up
        for _ in range(args.anchor_reps):
            seconds["anchor"].append(seconds_per_call(lambda: net(*inputs)))
            seconds["baseline"].append(seconds_per_call(lambda: base(*base_inputs)))
    matmul = max(matmul_before, matmul_gflops(2048, args.reps)["gflop_per_s"])
    median = statistics.median(seconds["anchor"])
    return {
        "source": shown(args.anchor_preset),
        "overrides": list(args.anchor_overrides),
        "height": cfg.height,
        "width": cfg.width,
        "params": sum(p.numel() for p in net.parameters()),
        "batch": 1,
        "steps": ANCHOR_STEPS,
        "gflop_per_forward": flops / 1e9,
        "median_forward_s": median,
        "s_per_scan": median * ANCHOR_STEPS,
        "gflop_per_s": flops / 1e9 / median,
        "matmul_gflop_per_s": matmul,
        "fraction_of_matmul": flops / 1e9 / median / matmul,
        "forward_s_reps": seconds["anchor"],
        "baseline_forward_s_reps": seconds["baseline"],
        "forward_over_baseline_forward_paired": paired_ratio(seconds["anchor"], seconds["baseline"]),
        "reps": args.anchor_reps,
    }


def net_sizes(nets: dict[str, Loaded], sources: dict[str, str]) -> list[dict]:
    """Params and GFLOP of a one-scan forward: each net at its size and at 64x1024, each anchor-preset stage."""
    cases = {}
    for stage, (_, cfg) in distinct_nets(nets).items():
        for height, width in ((cfg.height, cfg.width), (64, 1024)):
            source = sources["stage1"] if stage == "u4d" else sources[stage]  # a one-net U4D: both stages' file
            cases[(stage, source, height, width)] = cfg
    return [size_row(stage, source, cfg, height, width) for (stage, source, height, width), cfg in cases.items()]


def anchor_sizes(preset: Path, overrides: list[str]) -> list[dict]:
    """Params and GFLOP of a one-scan forward of each stage's net built from the anchor preset, at its size."""
    rows = []
    for stage in STAGES:
        cfg = preset_config(preset, stage, overrides)
        rows.append(size_row(stage, shown(preset), cfg, cfg.height, cfg.width))
    return rows


def source_names(sources: dict[str, Path | None], config: Path) -> dict[str, str]:
    """stage -> where its net came from: the checkpoint, or the preset it was built from (untrained)."""
    return {stage: shown(path) if path else f"{shown(config)} (untrained)" for stage, path in sources.items()}


def size_row(stage: str, source: str, cfg: DiffusionTrainConfig, height: int, width: int) -> dict:
    """Params and GFLOP of a one-scan forward of the net of `cfg` at height x width (on the meta device)."""
    sized = dataclasses.replace(cfg, height=height, width=width, crop_width=0, net=dataclasses.replace(cfg.net))
    net = build_net(sized).to("meta")
    return {
        "stage": stage,
        "source": source,
        "height": height,
        "width": width,
        "params": sum(p.numel() for p in net.parameters()),
        "gflop_per_forward": forward_flops(net, 1, height, width, "meta") / 1e9,
    }


def headline(samplers: list[dict], anchor: dict | None) -> dict:
    """Top-level figures: the first sampler at its smallest batch, and the anchor."""
    row = min(samplers[0]["generation"], key=lambda r: r["batch"])
    anchor_s = None if anchor is None else anchor["s_per_scan"]
    return {
        "u4d_s_per_scan": row["u4d_s_per_scan"],
        "baseline_s_per_scan": row["baseline_s_per_scan"],
        "paired_ratio": row["u4d_over_baseline_paired"],
        "anchor_s_per_scan": anchor_s,
        "anchor_over_u4d": None if anchor_s is None else anchor_s / row["u4d_s_per_scan"],
        "headline_sampler": samplers[0]["sampler"],
        "headline_steps": samplers[0]["steps"],
        "headline_stage1_steps": samplers[0]["stage1_steps"],
        "headline_batch": row["batch"],
    }


def goals(samplers: list[dict], unet: list[dict], anchor: dict | None, batches: list[int]) -> dict:
    """U4D <= 1.3x the baseline (first sampler, worst paired ratio over batches); UNets >= 50% of the matmul."""
    worst = max(row["u4d_over_baseline_paired"] for row in samplers[0]["generation"])
    largest = max(batches)
    fraction = next(r["fraction_of_matmul"] for r in unet if r["batch"] == largest and r["stage"] == "baseline")
    return {
        "u4d_over_baseline_max": GOAL_RATIO,
        "u4d_over_baseline_worst": worst,
        "u4d_ratio_met": worst <= GOAL_RATIO,
        "unet_fraction_min": GOAL_FRACTION,
        "unet_fraction": fraction,
        "unet_fraction_net": "baseline",
        "unet_fraction_batch": largest,
        "unet_fraction_met": fraction >= GOAL_FRACTION,
        "anchor_fraction": None if anchor is None else anchor["fraction_of_matmul"],
        "anchor_fraction_met": None if anchor is None else anchor["fraction_of_matmul"] >= GOAL_FRACTION,
    }


def table(header: list[str], rows: list[list]) -> list[str]:
    """Markdown table lines."""
    return [
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
        *("| " + " | ".join(str(cell) for cell in row) + " |" for row in rows),
    ]


def generation_table(samplers: list[dict]) -> list[str]:
    """Seconds per scan per sampler, batch and stage, the two ratios and the fraction of the matmul."""
    rows = [
        [
            f"{run['sampler']} {run['steps']} ({run['stage1_steps']})",
            row["batch"],
            f"{row['u4d_s_per_scan']:.3f}",
            f"{row['stage1_s_per_scan']:.3f}",
            f"{row['stage2_s_per_scan']:.3f}",
            f"{row['baseline_s_per_scan']:.3f}",
            f"{row['u4d_over_baseline']:.2f}x",
            f"{row['u4d_over_baseline_paired']:.2f}x",
            f"{run['gflop_per_scan']['u4d']:.1f} / {run['gflop_per_scan']['baseline']:.1f}",
            f"{row['u4d_fraction_of_matmul']:.0%} / {row['baseline_fraction_of_matmul']:.0%}",
        ]
        for run in samplers
        for row in run["generation"]
    ]
    header = ["sampler steps (stage 1)", "batch", "U4D s/scan", "stage 1", "stage 2", "baseline", "U4D/base"]
    return table([*header, "paired", "GFLOP/scan U4D / base", "of matmul U4D / base"], rows)


def anchor_lines(result: dict) -> list[str]:
    """The anchor table and what it is (forwards x steps, not a timed run)."""
    anchor = result["anchor"]
    if anchor is None:
        return ["Anchor skipped (`--anchor-reps 0`)."]
    minutes = anchor["s_per_scan"] / 60
    row = [
        f"R2DM-sized UNet ({anchor['source']})",
        f"{anchor['height']}x{anchor['width']}",
        f"{anchor['params']:,}",
        f"{anchor['gflop_per_forward']:.1f}",
        f"{anchor['median_forward_s']:.3f}",
        f"{anchor['s_per_scan']:.1f}",
        f"{anchor['gflop_per_s']:.2f}",
        f"{anchor['fraction_of_matmul']:.0%}",
    ]
    header = ["net", "H x W", "params", "GFLOP/forward", "forward s", f"x {anchor['steps']} = s/scan", "GFLOP/s"]
    speedup = f"{result['anchor_over_u4d']:.0f}x faster per scan than this anchor"
    if (anchor["height"], anchor["width"]) != (result["height"], result["width"]):
        speedup += f" (but at {result['height']}x{result['width']}: not comparable)"
    return [
        *table([*header, "of 2048² matmul"], [row]),
        "",
        f"Anchor = median of {anchor['reps']} one-scan forwards (batch 1, each followed by one of the baseline net: "
        f"paired ratio {anchor['forward_over_baseline_forward_paired']:.1f}x) x {anchor['steps']} (R2DM's DDPM "
        f"steps, one forward each). It is forwards x steps, not a timed {anchor['steps']}-step run: that would take "
        f"~{minutes:.0f} min per scan per repetition. U4D ({result['headline_sampler']} {result['headline_steps']} "
        f"steps, batch {result['headline_batch']}) is {speedup}.",
    ]


def other_tables(result: dict) -> list[str]:
    """Training steps, UNet forwards against the matmul, and net sizes."""
    lines = []
    if result["training"]:
        rows = [
            [r["stage"], f"{r['batch_size']} x {r['width']}", f"{r['steps_per_s']:.3f}", f"{r['median_step_s']:.4f}"]
            + [f"{r['gflop_per_step']:.2f}", f"{r['achieved_gflop_per_s']:.2f}"]
            for r in result["training"]
        ]
        lines += ["## Training steps (synthetic batches at the preset's batch size and crop width)", ""]
        lines += [*table(["stage", "batch x width", "steps/s", "step s", "GFLOP/step", "GFLOP/s"], rows), ""]
    mm = result["matmul"]
    rows = [
        [r["stage"], r["batch"], f"{r['gflop_per_forward']:.3f}", f"{r['median_forward_s']:.4f}"]
        + [f"{r['gflop_per_s']:.2f}", f"{r['fraction_of_matmul']:.0%}"]
        for r in result["unet"]
    ]
    lines += [f"## UNet forwards (matmul {mm['size']}² float32: {mm['gflop_per_s']:.2f} GFLOP/s)", ""]
    lines += [*table(["net", "batch", "GFLOP", "s", "GFLOP/s", "of matmul"], rows), ""]
    rows = [
        [r["stage"], f"{r['height']}x{r['width']}", f"{r['params']:,}", f"{r['gflop_per_forward']:.3f}", r["source"]]
        for r in result["nets"]
    ]
    return [*lines, "## Nets (one-scan forward)", "", *table(["net", "H x W", "params", "GFLOP", "source"], rows)]


def goal_lines(result: dict) -> list[str]:
    """The goals, met or not."""
    g = result["goals"]
    lines = [
        f"- U4D <= {GOAL_RATIO}x baseline per scan ({result['samplers'][0]['sampler']}, worst paired over batch "
        f"sizes): {'met' if g['u4d_ratio_met'] else 'NOT met'} ({g['u4d_over_baseline_worst']:.2f}x)",
        f"- UNet >= {GOAL_FRACTION:.0%} of the matmul (baseline net, batch {g['unet_fraction_batch']}): "
        f"{'met' if g['unet_fraction_met'] else 'NOT met'} ({g['unet_fraction']:.0%})",
    ]
    if g["anchor_fraction"] is not None:
        lines.append(
            f"- UNet >= {GOAL_FRACTION:.0%} of the matmul (anchor): "
            f"{'met' if g['anchor_fraction_met'] else 'NOT met'} ({g['anchor_fraction']:.0%})"
        )
    return lines


def markdown(result: dict) -> str:
    """The report: headline, generation, anchor, training, forwards, nets, goals."""
    machine, load = result["machine"], result["load_average_before"][0]
    anchor_s = result["anchor_s_per_scan"]
    head = [
        ["U4D (stage 1 + stage 2)", f"{result['u4d_s_per_scan']:.3f}"],
        ["baseline (R2DM-style, our net)", f"{result['baseline_s_per_scan']:.3f}"],
        ["U4D / baseline, paired", f"{result['paired_ratio']:.2f}x"],
        ["anchor (R2DM-sized net x 256 steps)", "skipped" if anchor_s is None else f"{anchor_s:.1f}"],
    ]
    nets = ", ".join(f"{stage}: {source}" for stage, source in result["net_sources"].items())
    lines = [
        f"# Generation speed at {result['height']}x{result['width']}",
        "",
        f"`{result['command']}`",
        "",
        f"{machine.get('cpu')}, {machine.get('cores')} cores, torch {machine.get('torch')}, {result['threads']} "
        f"threads, load average {load:.2f} -> {result['load_average_after'][0]:.2f}. Nets: {nets}.",
        "",
        f"## Seconds per scan ({result['headline_sampler']} {result['headline_steps']} steps, stage 1 "
        f"{result['headline_stage1_steps']}, batch {result['headline_batch']})",
        "",
        *table(["", "s/scan"], head),
        "",
        f"## Generation, seconds per scan ({result['reps']} interleaved repetitions, medians)",
        "",
        *generation_table(result["samplers"]),
        "",
        "## Anchor: R2DM's sampling cost",
        "",
        *anchor_lines(result),
        "",
        *other_tables(result),
        "",
        "## Goals",
        "",
        *goal_lines(result),
    ]
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line, with the defaults of the full run or of --quick."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=None, help="preset (default configs/u4d/cpu_hdl64.yaml)")
    parser.add_argument(
        "--net", type=Path, default=None,
        help="a one-net U4D (train-diffusion stage=u4d) checkpoint, run folder or weights for both stages",
    )  # fmt: skip
    parser.add_argument("--stage1", type=Path, default=None, help="stage-1 checkpoint or run folder")
    parser.add_argument("--stage2", type=Path, default=None, help="stage-2 checkpoint or run folder")
    parser.add_argument("--baseline", type=Path, default=None, help="baseline checkpoint or run folder")
    parser.add_argument("--weights", type=Path, default=None, help="folder of shipped nets (default weights/)")
    parser.add_argument("--no-weights", action="store_true", help="build the nets from the preset, not weights/")
    parser.add_argument(
        "--stage1-overrides", nargs="*", default=[], metavar="KEY=VALUE", help="applied to the stage-1 preset only"
    )
    parser.add_argument(
        "--sampler", choices=["ddpm", "ddim", "dpmpp2m", "dpmpp2m-sde"], default="dpmpp2m", help="timed sampler"
    )
    parser.add_argument("--steps", type=int, default=None, help="steps of stage 2 and the baseline (dpmpp2m 20)")
    parser.add_argument("--stage1-steps", type=int, default=None, help="steps of stage 1 (dpmpp2m 10, its SDE 6)")
    parser.add_argument("--compare-ddpm-steps", type=int, default=None, help="also DDPM with these steps (32; 0 off)")
    parser.add_argument("--compare-stage1-steps", type=int, default=None, help="its stage-1 steps (half of them)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8], help="generation batch sizes")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions; medians are reported (5)")
    parser.add_argument("--train-steps", type=int, default=None, help="timed training steps per stage, 0 skips (5)")
    parser.add_argument("--forward-calls", type=int, default=3, help="UNet forwards per repetition")
    parser.add_argument("--matmul-size", type=int, default=None, help="square matmul size (2048)")
    parser.add_argument("--anchor-preset", type=Path, default=ANCHOR_PRESET, help="R2DM-sized preset of the anchor")
    parser.add_argument(
        "--anchor-overrides", nargs="*", default=["net.num_res_blocks=1"],
        help="key=value changes of the anchor preset; the default makes full_hdl64 R2DM-sized (265 GFLOP, 44 M "
        "params per forward against R2DM's 235 GFLOP, 31 M; with 2 blocks per level it is 375 GFLOP, 63 M)",
    )  # fmt: skip
    parser.add_argument("--anchor-reps", type=int, default=None, help="timed anchor forwards, 0 skips (3; quick 0)")
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    parser.add_argument("--quick", action="store_true", help="tiny preset, 4 (2) steps, 3 reps, matmul 512")
    parser.add_argument("--out", type=Path, default=None, help="json path (default results/speed/generation_speed_HxW)")
    args = parser.parse_args(argv)
    quick = args.quick
    steps, stage1_steps = QUICK_STEPS if quick else DEFAULT_STEPS[args.sampler]
    compare = QUICK_STEPS[0] if quick else DEFAULT_STEPS["ddpm"][0]
    defaults = {
        "config": QUICK_PRESET if quick else PRESET,
        "steps": steps,
        "stage1_steps": stage1_steps,
        "compare_ddpm_steps": compare,
        "reps": 3 if quick else 5,
        "train_steps": 3 if quick else 5,
        "matmul_size": 512 if quick else 2048,
        "anchor_reps": 0 if quick else 3,
    }
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.compare_stage1_steps is None:
        args.compare_stage1_steps = max(1, args.compare_ddpm_steps // 2)
    if args.no_weights or (quick and args.weights is None):
        args.weights = None
    elif args.weights is None:
        args.weights = WEIGHTS
    if args.net is not None and (args.stage1 is not None or args.stage2 is not None or args.stage1_overrides):
        parser.error("--net is one net for both U4D stages: drop --stage1, --stage2 and --stage1-overrides")
    if args.stage1_overrides and args.stage1 is not None:
        parser.error("--stage1-overrides applies to a preset-built stage 1, not to a --stage1 checkpoint")
    counts = (args.steps, args.stage1_steps, args.compare_stage1_steps, args.reps, args.forward_calls, *args.batches)
    if min(counts) < 1 or min(args.compare_ddpm_steps, args.train_steps, args.anchor_reps) < 0:
        parser.error(
            "steps, reps, forward calls and batches must be >= 1; compare steps, train steps, anchor reps >= 0"
        )
    return args


def default_out(quick: bool, height: int, width: int) -> Path:
    """benchmarks/results/speed/generation_speed_HxW.json; --quick: the temp folder (never over the real results)."""
    folder = Path(tempfile.gettempdir()) if quick else REPO / "benchmarks" / "results" / "speed"
    return folder / f"generation_speed{'_quick' if quick else ''}_{height}x{width}.json"


def main(argv: list[str] | None = None) -> int:
    """Time everything, print the report, write the json and the md."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    try:
        sources = checkpoint_sources(args)
        nets = load_nets(args, sources)
        runs = sampler_runs(args)
        print(f"matmul {args.matmul_size}² ...", flush=True)
        matmul = matmul_gflops(args.matmul_size, args.reps)
        flops = {stage: forward_flops(net, 1, cfg.height, cfg.width) for stage, (net, cfg) in nets.items()}
        print("generation ...", flush=True)
        samplers = time_generation(nets, runs, args, flops, matmul["gflop_per_s"])
        print("training ...", flush=True)
        training = time_training(nets, args)
        print("UNet forwards ...", flush=True)
        unet = time_unet(nets, args, matmul["gflop_per_s"])
        print("anchor ...", flush=True)
        anchor = time_anchor(nets, args)
        names = source_names(sources, args.config)
        sizes = net_sizes(nets, names) + anchor_sizes(args.anchor_preset, list(args.anchor_overrides))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    _, cfg = nets["baseline"]
    result = {
        "benchmark": "generation_speed",
        **headline(samplers, anchor),
        "command": " ".join(
            ["python", "benchmarks/bench_generation_speed.py", *(sys.argv[1:] if argv is None else argv)]
        ),
        "machine": host_info(),
        "threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(default)"),
        "load_average_before": list(load_before),
        "load_average_after": list(os.getloadavg()),
        "quick": args.quick,
        "config": shown(args.config),
        "stage1_overrides": args.stage1_overrides,
        "net_sources": names,
        "height": cfg.height,
        "width": cfg.width,
        "reps": args.reps,
        "samplers": samplers,
        "anchor": anchor,
        "training": training,
        "matmul": matmul,
        "unet": unet,
        "nets": sizes,
    }
    result["goals"] = goals(samplers, unet, anchor, args.batches)
    report = markdown(result)
    print("\n" + report)
    out = args.out or default_out(args.quick, cfg.height, cfg.width)
    atomic_write_json(out, result)
    atomic_write_text(out.with_suffix(".md"), report)
    print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
