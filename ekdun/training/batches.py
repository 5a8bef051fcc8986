"""Training batches: the dataset kept on the device when it fits (a batch is an
``index_select`` there), else a DataLoader with workers and pinned memory. Both follow
:func:`ekdun.training.distributed.global_batches`, a function of ``(seed, epoch)`` only.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from ekdun.training import distributed as D

# Fractions of memory a resident dataset may take (the model, activations and optimizer
# state need the rest).
CUDA_FREE_FRACTION = 0.25
CPU_BUDGET_BYTES = 4 * 2**30


def fits_on_device(dataset: Dataset, device: torch.device) -> bool:
    """Whether all ``(scene, measurement)`` pairs as float32 tensors (sized from the first)
    may be kept on ``device`` (see the budgets above)."""
    x, y = dataset[0]
    need = len(dataset) * (x.numel() + y.numel()) * 4  # type: ignore[arg-type]
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        return need <= CUDA_FREE_FRACTION * free
    return need <= CPU_BUDGET_BYTES


class _EpochBatches(Sampler[list[int]]):
    """This rank's share of every global batch of the current epoch (``set_epoch``)."""

    def __init__(self, n_items: int, batch_size: int, seed: int, ctx: D.DistContext) -> None:
        self.n_items, self.batch_size, self.seed, self.ctx = n_items, batch_size, seed, ctx
        self.epoch = 1

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self) -> Iterator[list[int]]:
        for batch in D.global_batches(self.n_items, self.batch_size, self.seed, self.epoch):
            yield D.local_share(batch, self.ctx.rank, self.ctx.world_size)

    def __len__(self) -> int:
        return self.n_items // self.batch_size


class BatchSource:
    """The contiguous ``(b, C, H', W')`` training batches of every epoch, on the device.

    Parameters
    ----------
    dataset : Dataset
        ``(scene, measurement)`` pairs of ``(C, H', W')`` float32 tensors.
    batch_size : int
        Global batch size (each rank gets its contiguous share).
    seed : int
    ctx : DistContext
    resident : bool or None
        Keep the dataset on the device; ``None``: when it fits (:func:`fits_on_device`).
    workers : int
        DataLoader worker processes of the streamed path.
    """

    def __init__(self, dataset: Dataset, batch_size: int, seed: int, ctx: D.DistContext,
                 resident: bool | None = None, workers: int = 2) -> None:
        self.device = ctx.device
        n = len(dataset)  # type: ignore[arg-type]
        self.sampler = _EpochBatches(n, batch_size, seed, ctx)
        D.global_batches(n, batch_size, seed, 1)  # configuration errors before any loading
        self.resident = fits_on_device(dataset, ctx.device) if resident is None else resident
        self.scenes: torch.Tensor | None = None
        self.measurements: torch.Tensor | None = None
        self.loader: DataLoader | None = None
        if self.resident:
            items = [dataset[i] for i in range(n)]
            self.scenes = torch.stack([it[0] for it in items]).to(ctx.device)
            self.measurements = torch.stack([it[1] for it in items]).to(ctx.device)
        else:
            cuda = ctx.device.type == "cuda"
            self.loader = DataLoader(dataset, batch_sampler=self.sampler,
                                     num_workers=workers, pin_memory=cuda,
                                     persistent_workers=workers > 0)

    def __len__(self) -> int:
        return len(self.sampler)

    def epoch(self, epoch: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """``(scenes, measurements)`` batches ``(b, C, H', W')`` of ``epoch``, on the device."""
        self.sampler.set_epoch(epoch)
        if self.loader is None:
            assert self.scenes is not None and self.measurements is not None
            # One host-to-device copy of the epoch's indices (a copy per step would wait for
            # the device every step); each batch is then a slice of it.
            order = torch.as_tensor(list(self.sampler), dtype=torch.long).to(self.device)
            for index in order:
                yield self.scenes.index_select(0, index), self.measurements.index_select(0, index)
            return
        for x, y in self.loader:
            # Pinned memory + non_blocking: the copy overlaps the previous step's kernels.
            yield x.to(self.device, non_blocking=True), y.to(self.device, non_blocking=True)
