"""Distributed data parallel helpers (``torchrun``): process group, device, batches. Every
process trains on its share of each global batch (``--batch-size``); only rank 0 writes.
"""

from __future__ import annotations

import gc
import importlib
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from ekdun.errors import ConfigurationError


@dataclass(frozen=True)
class DistContext:
    """Rank, world size and device of this process."""

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def setup(device: str = "auto") -> DistContext:
    """Join the process group when launched by ``torchrun`` (``WORLD_SIZE`` > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    from ekdun.device import resolve_device

    dev = resolve_device(device, local_rank)
    if world > 1 and not dist.is_initialized():
        backend = "nccl" if dev.type == "cuda" else "gloo"
        if dev.type == "cuda":
            torch.cuda.set_device(dev)
        # torch.distributed.nn.functional binds ``group.WORLD`` as default arguments when it is
        # first imported, which DDP's constructor does. Imported after the group exists, those
        # defaults keep the group alive past destroy_process_group, and its gloo threads end
        # only while the interpreter shuts down (the likeliest place of the rare rank abort
        # "terminate called without an active exception" seen in CI). Imported first, the
        # defaults hold None.
        importlib.import_module("torch.distributed.nn")
        dist.init_process_group(backend=backend)
    return DistContext(rank, world, local_rank, dev)


def global_batches(n_items: int, global_batch: int, seed: int, epoch: int) -> list[list[int]]:
    """The epoch's global batches: a permutation seeded by ``(seed, epoch)`` cut into full
    batches of ``global_batch`` >= 1 (an incomplete last batch is dropped)."""
    if n_items < global_batch:
        raise ConfigurationError(f"the dataset has {n_items} pairs, fewer than one batch "
                                 f"(--batch-size {global_batch})")
    generator = torch.Generator().manual_seed(int(seed) * 100_003 + int(epoch))
    order = torch.randperm(n_items, generator=generator).tolist()
    return [order[i:i + global_batch]
            for i in range(0, n_items - global_batch + 1, global_batch)]


def local_share(batch: list[int], rank: int, world_size: int) -> list[int]:
    """This rank's contiguous share of a global batch (``train`` checked that it splits)."""
    per = len(batch) // world_size
    return batch[rank * per:(rank + 1) * per]


def all_mean(value: float, ctx: DistContext) -> float:
    """Mean of a scalar over ranks (for logs)."""
    if not ctx.distributed:
        return value
    t = torch.tensor([value], dtype=torch.float64,
                     device=ctx.device if ctx.device.type == "cuda" else "cpu")
    dist.all_reduce(t)
    return float(t.item()) / ctx.world_size


def barrier(ctx: DistContext) -> None:
    if ctx.distributed:
        dist.barrier()


def teardown(ctx: DistContext) -> None:
    """Leave the process group joined by :func:`setup`, once the DDP wrapper is dropped (it
    holds the group in a reference cycle, collected here first)."""
    if ctx.distributed and dist.is_initialized():
        gc.collect()
        dist.destroy_process_group()
