"""Device choice and torch.distributed set-up for `torchrun` (gloo on CPU, nccl on CUDA)."""

from __future__ import annotations

import gc
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from u4d_aug.errors import InputError


def resolve_device(device: str) -> torch.device:
    """'auto' -> cuda when available else cpu; 'cpu', 'cuda', 'cuda:N' as given (one `device` setting everywhere)."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"device '{device}' requested but CUDA is not available here; use device=cpu or auto")
    try:
        return torch.device(device)
    except RuntimeError:
        raise InputError(f"device: expected auto, cpu, cuda or cuda:N, got '{device}'") from None


@dataclass(frozen=True)
class DistInfo:
    """Where this process stands: rank, world size, local rank and its device."""

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str = "auto") -> DistInfo:
    """Join the process group when started by torchrun (WORLD_SIZE > 1); otherwise a single process."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    dev = resolve_device(device)
    if dev.type == "cuda" and world_size > 1:
        dev = torch.device("cuda", local_rank)
        torch.cuda.set_device(dev)
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if dev.type == "cuda" else "gloo")
    return DistInfo(rank=rank, world_size=world_size, local_rank=local_rank, device=dev)


def barrier() -> None:
    """Wait for every rank (no-op in a single process)."""
    if dist.is_available() and dist.is_initialized():
        dist.barrier()


def all_reduce_mean(value: torch.Tensor) -> torch.Tensor:
    """Mean of a tensor over ranks (identity in a single process)."""
    if dist.is_available() and dist.is_initialized():
        value = value.clone()
        dist.all_reduce(value, op=dist.ReduceOp.SUM)
        value /= dist.get_world_size()
    return value


def dist_initialized() -> bool:
    """Whether this process is one rank of a joined process group."""
    return dist.is_available() and dist.is_initialized()


def ranks_where(flag: bool) -> list[int]:
    """The ranks on which `flag` holds ([0] or [] in a single process): a collective every rank must call."""
    if not dist_initialized():
        return [0] if flag else []
    flags = torch.zeros(dist.get_world_size(), dtype=torch.int64)
    flags[dist.get_rank()] = int(flag)
    dist.all_reduce(flags, op=dist.ReduceOp.SUM)
    return [rank for rank, bad in enumerate(flags.tolist()) if bad]


def all_reduce_sum(value: torch.Tensor) -> torch.Tensor:
    """Sum of a tensor over ranks (identity in a single process)."""
    if dist.is_available() and dist.is_initialized():
        value = value.clone()
        dist.all_reduce(value, op=dist.ReduceOp.SUM)
    return value


def shard(items: list, rank: int, world_size: int) -> list:
    """Every world_size-th item starting at rank: a deterministic split of work across ranks."""
    return items[rank::world_size]


def budget_used(elapsed_seconds: float, max_minutes: float) -> bool:
    """Wall-clock budget check (max_minutes <= 0: none), decided by rank 0 so every rank stops at the same step."""
    return max_minutes > 0 and budget_fraction(elapsed_seconds, max_minutes) >= 1.0


def budget_fraction(elapsed_seconds: float, max_minutes: float) -> float:
    """Share of the wall-clock budget used, in [0, 1] (0 without a budget), rank 0's value on every rank."""
    if max_minutes <= 0:
        return 0.0
    fraction = torch.tensor(min(1.0, elapsed_seconds / (60.0 * max_minutes)), dtype=torch.float64)
    if dist.is_available() and dist.is_initialized():
        dist.broadcast(fraction, src=0)
    return float(fraction)


def cleanup() -> None:
    """Leave the process group if one was joined, once nothing of this process still holds it.

    A DistributedDataParallel wrapper sits in reference cycles, so its reducer (which keeps the group alive) would
    otherwise be freed at interpreter exit, after `destroy_process_group`: gloo's threads then end in a C++
    `terminate called without an active exception` (SIGABRT) on a rank that finished fine. Collecting first frees
    it here, while the group is still whole.
    """
    if dist.is_available() and dist.is_initialized():
        gc.collect()
        dist.destroy_process_group()
