"""Evaluate reconstruction networks: quality, size, speed and memory (Tables 1 and 2)."""

from __future__ import annotations

import os
import statistics
import threading
import time
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Dataset

from ekdun.evaluation.metrics import LPIPSMetric, psnr, ssim
from ekdun.models.unrolled import UnrolledNetwork


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return 0


class _PeakRSS:
    """Peak resident memory above the starting level, sampled every 2 ms (CPU runs)."""

    def __init__(self) -> None:
        self.base = _rss_bytes()
        self.peak = self.base
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, _rss_bytes())
            time.sleep(0.002)

    def __enter__(self) -> _PeakRSS:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_bytes())


@torch.no_grad()
def evaluate_model(model: UnrolledNetwork, dataset: Dataset, label: str = "",
                   lpips: LPIPSMetric | None = None, device: str | torch.device = "cpu",
                   warmup: int = 1) -> dict[str, Any]:
    """PSNR, SSIM (LPIPS when available), parameters, runtime and peak memory.

    Images are reconstructed one at a time (batch 1); outputs are clipped to ``[0, 1]``
    before the metrics. Runtime is the median wall time per image after ``warmup`` images.
    Peak memory is ``torch.cuda.max_memory_allocated`` on CUDA and the sampled peak of the
    process' resident memory above its level before the run on CPU (an estimate).
    """
    device = torch.device(device)
    model = model.to(device).eval()
    n = len(dataset)  # type: ignore[arg-type]
    psnrs, ssims, lpipss, times = [], [], [], []
    for i in range(min(warmup, n)):
        model(dataset[i][1][None].to(device))
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    with _PeakRSS() as mem:
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
            else mem.peak - mem.base)
    return {
        "label": label, "images": n,
        "psnr": statistics.fmean(psnrs), "ssim": statistics.fmean(ssims),
        "lpips": statistics.fmean(lpipss) if lpipss else None,
        "parameters": model.parameter_count(),
        "runtime_ms_median": 1e3 * statistics.median(times),
        "peak_memory_mib": peak / 2**20,
        "memory_kind": "cuda max allocated" if device.type == "cuda"
        else "CPU RSS increase (sampled)",
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
