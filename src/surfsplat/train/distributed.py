"""Data-parallel plumbing: one process per device, PyTorch's own DDP, torchrun's env:// rendezvous.

    torchrun --nproc_per_node 4 -m surfsplat train --preset small ...   # 4 ranks
    python -m surfsplat train --preset tiny                              # 1 rank, same code path

torchrun sets RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT; with WORLD_SIZE > 1 the
process group starts with NCCL on GPUs and gloo on CPUs. Rank 0 is the single writer of
checkpoints and logs; metrics are reduced over all ranks before anyone reports them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.distributed as dist
from torch import Tensor

from ..utils.checks import SurfSplatInputError


@dataclass(frozen=True)
class DistributedContext:
    """Where this process sits in the run."""

    rank: int  # global rank, 0 .. world_size - 1
    world_size: int  # number of processes
    local_rank: int  # rank on this machine (selects the GPU)
    device: torch.device  # the device this rank computes on

    @property
    def is_main(self) -> bool:
        """True on the one process that writes checkpoints, logs and the progress bar."""
        return self.rank == 0

    @property
    def is_distributed(self) -> bool:
        return self.world_size > 1


def _env_int(name: str, default: int) -> int:
    value = os.environ.get(name)
    if value is None:
        return default
    try:
        return int(value)
    except ValueError:
        raise SurfSplatInputError(f"environment variable {name}: expected an integer, got {value!r}") from None


def init_distributed(device: Literal["auto", "cpu", "cuda"] = "auto") -> DistributedContext:
    """Join the process group described by torchrun's environment (or run alone without one)."""
    world_size = _env_int("WORLD_SIZE", 1)
    rank = _env_int("RANK", 0)
    local_rank = _env_int("LOCAL_RANK", 0)
    if world_size < 1 or not 0 <= rank < world_size:
        raise SurfSplatInputError(f"environment: RANK={rank} is not a rank of WORLD_SIZE={world_size}")
    if device == "cuda" and not torch.cuda.is_available():
        raise SurfSplatInputError("device: 'cuda' requested but no CUDA device is available")
    use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if use_cuda:
        if local_rank >= torch.cuda.device_count():
            raise SurfSplatInputError(
                f"environment: LOCAL_RANK={local_rank} but only {torch.cuda.device_count()} CUDA devices are visible"
            )
        torch.cuda.set_device(local_rank)
        dev = torch.device("cuda", local_rank)
    else:
        dev = torch.device("cpu")
    if world_size > 1 and not dist.is_initialized():
        for name in ("MASTER_ADDR", "MASTER_PORT"):
            if name not in os.environ:
                raise SurfSplatInputError(
                    f"environment: WORLD_SIZE={world_size} but {name} is not set (launch with torchrun)"
                )
        dist.init_process_group(
            backend="nccl" if use_cuda else "gloo", init_method="env://", rank=rank, world_size=world_size
        )
    return DistributedContext(rank=rank, world_size=world_size, local_rank=local_rank, device=dev)


def shutdown(ctx: DistributedContext) -> None:
    if ctx.is_distributed and dist.is_initialized():
        dist.destroy_process_group()


def all_reduce_sum(values: Tensor, ctx: DistributedContext) -> Tensor:
    """Element-wise sum over ranks (a copy; float64 so sums of many metrics stay exact enough)."""
    out = values.detach().to(torch.float64).clone()
    if ctx.is_distributed:
        # gloo reduces CPU tensors only; NCCL needs them on the rank's GPU.
        out = out.to(ctx.device)
        dist.all_reduce(out, op=dist.ReduceOp.SUM)
    return out.cpu()


def all_reduce_mean(values: Tensor, ctx: DistributedContext) -> Tensor:
    """Element-wise mean over ranks."""
    return all_reduce_sum(values, ctx) / ctx.world_size


def all_gather_objects(obj: Any, ctx: DistributedContext) -> list[Any]:
    """Every rank's `obj` (picklable), in rank order; [obj] without a process group."""
    if not ctx.is_distributed:
        return [obj]
    out: list[Any] = [None] * ctx.world_size
    dist.all_gather_object(out, obj)
    return out


def barrier(ctx: DistributedContext) -> None:
    if ctx.is_distributed:
        dist.barrier()
