"""One epoch of training: Adam steps on the MSE (plus a study's extra loss) under the run's
AMP mode, the loss summed on the device and read once per epoch.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ekdun import device as acc
from ekdun.nets.unrolled import UnrolledNetwork
from ekdun.training import distributed as D
from ekdun.training.batches import BatchSource


@dataclass
class Loop:
    """What every training step uses (``net``: the network wrapped for an extra loss
    (``extra_loss``: ``net(y, x) -> (x̂, extra)``), DDP and compile)."""

    model: UnrolledNetwork
    net: nn.Module
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    scaler: torch.amp.GradScaler
    amp: str
    ctx: D.DistContext
    extra_loss: bool = False


def train_epoch(loop: Loop, source: BatchSource, epoch: int, batch_size: int,
                metadata: dict[str, Any], *, desc: str | None, log_every: int,
                time_compile: bool) -> dict[str, Any]:
    """One epoch; its history row. ``desc``: the progress bar's label (``None``: no bar);
    ``time_compile``: record the first step's time as ``metadata["compile_warmup_s"]``."""
    ctx = loop.ctx
    t0 = time.perf_counter()
    loop.model.train()
    bar = None
    if desc is not None:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(source), desc=desc, unit="batch", leave=False)
    # The epoch's loss is summed on the device: reading it (.item()) makes the host wait
    # for the device, so that happens only at log points and at the end of the epoch.
    total = torch.zeros((), dtype=torch.float64, device=ctx.device)
    total_extra = torch.zeros((), dtype=torch.float64, device=ctx.device)
    count = 0
    for x, y in source.epoch(epoch):
        loss, extra = _step(loop, x, y)
        total += loss
        if extra is not None:
            total_extra += extra
        count += 1
        if time_compile and count == 1:
            acc.cuda_synchronize(ctx.device)
            metadata["compile_warmup_s"] = round(time.perf_counter() - t0, 3)
        if bar is not None:
            bar.update()
            if count % max(log_every, 1) == 0:
                bar.set_postfix(loss=f"{total.item() / count:.3g}")
    if bar is not None:
        bar.close()
    lr = loop.optimizer.param_groups[0]["lr"]
    loop.scheduler.step()
    mean_loss = D.all_mean(total.item() / max(count, 1), ctx)
    seconds = time.perf_counter() - t0
    row = {"epoch": epoch, "train_loss": mean_loss, "lr": lr, "seconds": round(seconds, 3),
           "images_per_second": round(count * batch_size / max(seconds, 1e-9), 3)}
    if loop.extra_loss:
        # the MSE stays train_loss (comparable across studies); the extra term beside it
        row["extra_loss"] = D.all_mean(total_extra.item() / max(count, 1), ctx)
    return row


def _step(loop: Loop, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor | None]:
    """One optimizer step; the batch's MSE and extra loss (if any), detached."""
    loop.optimizer.zero_grad(set_to_none=True)
    with acc.autocast(loop.amp, loop.ctx.device):
        out, extra = loop.net(y, x) if loop.extra_loss else (loop.net(y), None)
    loss = nn.functional.mse_loss(out.float(), x)
    loop.scaler.scale(loss if extra is None else loss + extra).backward()
    loop.scaler.step(loop.optimizer)
    loop.scaler.update()
    return loss.detach(), None if extra is None else extra.detach()
