"""Evaluate reconstruction networks: quality, size, speed and memory (Tables 1 and 2)."""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Dataset

from ekdun.evaluation.metrics import LPIPSMetric, psnr, ssim
from ekdun.models.unrolled import UnrolledNetwork


def cpu_peak_memory(model: UnrolledNetwork, y: torch.Tensor) -> int:
    """Peak of torch's CPU allocations (bytes) during one forward pass, from the profiler's
    memory events (an estimate: allocations made and freed inside one operator count at the
    operator's end)."""
    from torch.profiler import ProfilerActivity, profile

    with torch.no_grad(), profile(activities=[ProfilerActivity.CPU],
                                  profile_memory=True) as prof:
        model(y)
    events = sorted(prof.events(), key=lambda e: e.time_range.start if e.name == "[memory]"
                    else e.time_range.end)
    current = peak = 0
    for e in events:
        current += e.cpu_memory_usage if e.name == "[memory]" else e.self_cpu_memory_usage
        peak = max(peak, current)
    return peak


@torch.no_grad()
def evaluate_model(model: UnrolledNetwork, dataset: Dataset, label: str = "",
                   lpips: LPIPSMetric | None = None, device: str | torch.device = "cpu",
                   warmup: int = 1) -> dict[str, Any]:
    """PSNR, SSIM (LPIPS when available), parameters, runtime and peak memory.

    Images are reconstructed one at a time (batch 1); outputs are clipped to ``[0, 1]``
    before the metrics. Runtime is the median wall time per image after ``warmup`` images.
    Peak memory is ``torch.cuda.max_memory_allocated`` on CUDA and, on CPU, the peak of
    torch's allocations during one profiled forward pass (:func:`cpu_peak_memory`).
    """
    device = torch.device(device)
    model = model.to(device).eval()
    n = len(dataset)  # type: ignore[arg-type]
    psnrs, ssims, lpipss, times = [], [], [], []
    for i in range(min(warmup, n)):
        model(dataset[i][1][None].to(device))
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    for i in range(n):
        x, y = dataset[i]
        x, y = x[None].to(device), y[None].to(device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        out = model(y)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - t0)
        out = out.clamp(0, 1)
        psnrs.append(float(psnr(out, x)[0]))
        ssims.append(float(ssim(out, x)[0]))
        if lpips is not None and lpips.available:
            lpipss.append(float(lpips(out, x)[0]))
    peak = (torch.cuda.max_memory_allocated(device) if device.type == "cuda"
            else cpu_peak_memory(model, dataset[0][1][None].to(device)))
    return {
        "label": label, "images": n,
        "psnr": statistics.fmean(psnrs), "ssim": statistics.fmean(ssims),
        "lpips": statistics.fmean(lpipss) if lpipss else None,
        "parameters": model.parameter_count(),
        "runtime_ms_median": 1e3 * statistics.median(times),
        "peak_memory_mib": peak / 2**20,
        "memory_kind": "cuda max allocated" if device.type == "cuda"
        else "torch CPU allocations (profiler estimate)",
        "device": str(device),
    }


def save_reconstructions(model: UnrolledNetwork, dataset: Dataset, out_dir: Path,
                         limit: int = 4) -> None:
    """A few reconstructions as ``.npy`` for figures."""
    import numpy as np

    out_dir.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        for i in range(min(limit, len(dataset))):  # type: ignore[arg-type]
            out = model(dataset[i][1][None]).clamp(0, 1)[0].numpy()
            np.save(out_dir / f"{i:03d}.npy", np.moveaxis(out, 0, -1))
