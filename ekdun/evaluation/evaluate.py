"""Evaluate reconstruction networks: quality, size, speed and memory (Tables 1 and 2)."""

from __future__ import annotations

import hashlib
import os
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Dataset

from ekdun.device import cuda_synchronize, resolve_device
from ekdun.errors import InvalidInputError
from ekdun.evaluation.metrics import SSIM_MARGIN, LPIPSMetric, psnr, ssim, ssim_map
from ekdun.nets.unrolled import UnrolledNetwork
from psfkit.forward.zones import ZONE_NAMES, field_zones


def cpu_peak_memory(model: UnrolledNetwork, y: torch.Tensor) -> int:
    """Peak of torch's CPU allocations (bytes) during one forward pass, estimated from the
    profiler's memory events."""
    # Kineto logs a "USDT ... profiler_start/stop" notice on stderr for every profiled pass at
    # its highest level (5); 6 keeps eval's stderr for errors. Read when the profiler first
    # starts in a process, so a user's own setting wins.
    os.environ.setdefault("KINETO_LOG_LEVEL", "6")
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


class ZoneScores:
    """PSNR and SSIM of reconstructions in each field zone (:mod:`psfkit.forward.zones`): the
    PSNR of the zone's MSE, and the mean of the SSIM map over the zone's pixels of the map's
    valid region (``None`` where there are none)."""

    def __init__(self, shape: tuple[int, int],
                 optical_center: tuple[float, float] | None = None) -> None:
        self.zones = field_zones(shape, optical_center)
        self.masks = {name: torch.from_numpy(mask)
                      for name, mask in self.zones.masks().items()}
        inner = self.zones.cropped(SSIM_MARGIN)
        self.inner = {name: torch.from_numpy(mask) for name, mask in inner.masks().items()}
        self.psnr: dict[str, list[float]] = {name: [] for name in ZONE_NAMES}
        self.ssim: dict[str, list[float]] = {name: [] for name in ZONE_NAMES}

    def add(self, output: torch.Tensor, target: torch.Tensor) -> None:
        """Score one ``(1, C, H, W)`` reconstruction ``output`` against ``target``."""
        local = ssim_map(output, target)[0]
        for name in ZONE_NAMES:
            self.psnr[name].append(float(psnr(output, target,
                                              mask=self.masks[name].to(output.device))[0]))
            if self.inner[name].any():
                self.ssim[name].append(float(local[:, self.inner[name].to(local.device)]
                                             .mean()))

    def summary(self) -> dict[str, Any]:
        """``{zone: {psnr, ssim, psnr_per_pair, ssim_per_pair}}`` (means over images)."""
        return {name: {"psnr": statistics.fmean(self.psnr[name]),
                       "ssim": statistics.fmean(self.ssim[name]) if self.ssim[name] else None,
                       "psnr_per_pair": self.psnr[name],
                       "ssim_per_pair": self.ssim[name] or None}
                for name in ZONE_NAMES}


@torch.no_grad()
def evaluate_model(model: UnrolledNetwork, dataset: Dataset, label: str = "",
                   lpips: LPIPSMetric | None = None, device: str | torch.device = "cpu",
                   warmup: int = 1, optical_center: tuple[float, float] | None = None
                   ) -> dict[str, Any]:
    """PSNR, SSIM (LPIPS when available), also per image and by field zone, parameters,
    runtime and peak memory.

    Batch 1, outputs clipped to ``[0, 1]``; runtime: the median per image after ``warmup``
    images; peak memory: CUDA's max allocated, on CPU :func:`cpu_peak_memory`. ``by_zone``:
    the three equal-area radial zones around ``optical_center`` (:class:`ZoneScores`).
    """
    device = resolve_device(device)
    model = model.to(device).eval()
    n = len(dataset)  # type: ignore[arg-type]
    psnrs, ssims, lpipss, times = [], [], [], []
    zones = ZoneScores(tuple(dataset[0][0].shape[-2:]), optical_center) if n else None
    for i in range(min(warmup, n)):
        model(dataset[i][1][None].to(device))
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    for i in range(n):
        x, y = dataset[i]
        x, y = x[None].to(device), y[None].to(device)
        cuda_synchronize(device)
        t0 = time.perf_counter()
        out = model(y)
        cuda_synchronize(device)
        times.append(time.perf_counter() - t0)
        out = out.clamp(0, 1)
        psnrs.append(float(psnr(out, x)[0]))
        ssims.append(float(ssim(out, x)[0]))
        if zones is not None:
            zones.add(out, x)
        if lpips is not None and lpips.available:
            lpipss.append(float(lpips(out, x)[0]))
    peak = (torch.cuda.max_memory_allocated(device) if device.type == "cuda"
            else cpu_peak_memory(model, dataset[0][1][None].to(device)))
    return {
        "label": label, "images": n,
        "psnr": statistics.fmean(psnrs), "ssim": statistics.fmean(ssims),
        "lpips": statistics.fmean(lpipss) if lpipss else None,
        "psnr_per_pair": psnrs, "ssim_per_pair": ssims,
        "by_zone": zones.summary() if zones is not None else None,
        "zones": zones.zones.describe() if zones is not None else None,
        "parameters": model.parameter_count(),
        "runtime_ms_median": 1e3 * statistics.median(times),
        "peak_memory_mib": peak / 2**20,
        "memory_kind": "cuda max allocated" if device.type == "cuda"
        else "torch CPU allocations (profiler estimate)",
        "device": str(device),
    }


def recorded_optical_center(metadata: dict[str, Any]) -> tuple[float, float] | None:
    """The optical centre ``(v_c, u_c)`` a checkpoint's kernel metadata records, if any."""
    centre = (metadata.get("kernel_metadata") or {}).get("optical_center")
    return (float(centre[0]), float(centre[1])) if centre else None


def checkpoint_path(item: str | os.PathLike) -> Path:
    """``item`` itself, or ``item/checkpoint.pt`` when ``item`` is a run folder."""
    path = Path(item)
    return path / "checkpoint.pt" if path.is_dir() else path


def evaluation_pairs(data: str | os.PathLike, trained: dict[str, Any],
                     include_training: bool = False,
                     channel_order: str | None = None) -> tuple[Any, str]:
    """The pairs of ``data`` on which a checkpoint may be scored, read as it was trained; on
    the training folder itself only the pairs training held out.

    Parameters
    ----------
    data : path-like
        Pairs folder, or a virtual-bench dataset (its ``test/`` split).
    trained : dict
        The checkpoint's ``metadata["data"]`` (``{}`` for older checkpoints).
    include_training : bool
        Score every pair of the training folder anyway.
    channel_order : {"RGB", "BGR"}, optional
        ``--channel-order`` (default: the folder's, else the checkpoint's record, else RGB).

    Returns
    -------
    (PairsDataset, str)
        The dataset and a note saying which pairs it holds.

    Raises
    ------
    InvalidInputError
        ``data`` is the folder the checkpoint was trained on, with no pair held out.
    """
    from ekdun.data.pairs import PairsDataset, recorded_read_options
    from ekdun.data.virtual_bench import resolve_split

    root = resolve_split(data, "test")
    recorded = recorded_read_options(trained)
    factor = recorded.downsample or 1
    same = bool(trained.get("root")) and Path(trained["root"]).resolve() == root.resolve()
    held = list(trained.get("holdout") or [])
    only: list[str] = []
    if same and not include_training:
        if not held:
            raise InvalidInputError(
                f"{data}: the checkpoint was trained on every pair of this folder, so its "
                "scores would be training scores; hold pairs out (ekdun train --holdout NAME), "
                "evaluate on another folder, or pass --include-training")
        only, note = held, f"the {len(held)} pair(s) training held out: {', '.join(held)}"
    else:
        note = "every pair, training pairs included" if same else f"every pair of {root}"
    return PairsDataset(root, channel_order, downsample=factor, only=only,
                        recorded=recorded), note


def seed_kernels_identity(doc: dict[str, Any]) -> dict[str, Any]:
    """Which seed kernels a checkpoint was trained from: ``seed_kernels_sha`` (12 hex digits
    of the SHA-256 of its float32 initial kernels) and ``seed_kernels_one_psf``
    (``Kv = Kh = Kbase``); both None without initial kernels."""
    kernels = doc.get("initial_kernels")
    if kernels is None:
        return {"seed_kernels_sha": None, "seed_kernels_one_psf": None}
    k = kernels.detach().cpu().to(torch.float32).contiguous()
    one_psf = bool(k.shape[0] > 1 and all(torch.equal(k[0], k[i]) for i in range(1, k.shape[0])))
    return {"seed_kernels_sha": hashlib.sha256(k.numpy().tobytes()).hexdigest()[:12],
            "seed_kernels_one_psf": one_psf}


def evaluate_checkpoints(checkpoints: Sequence[str | os.PathLike], data: str | os.PathLike,
                         lpips: LPIPSMetric | None = None, device: str | torch.device = "auto",
                         log: Callable[[str], Any] | None = None,
                         include_training: bool = False,
                         channel_order: str | None = None) -> list[dict[str, Any]]:
    """Evaluate trained runs on held-out pairs: the rows of Tables 1 and 2.

    Parameters
    ----------
    checkpoints : sequence of path-like
        ``checkpoint.pt`` files or run folders.
    data : path-like
        Pairs folder or virtual-bench dataset, read per run by :func:`evaluation_pairs`.
    lpips : LPIPSMetric, optional
        Rows get ``lpips: None`` when absent or unavailable.
    device : str or torch.device
    log : callable, optional
        Called with one line per evaluated run.
    include_training, channel_order
        As :func:`evaluation_pairs`.

    Returns
    -------
    list of dict
        :func:`evaluate_model` rows plus ``checkpoint``, ``model``, ``schedule``, ``epochs``,
        ``seed``, ``kernel_param``, ``physics_weight``, ``kernel_lr_scale`` and
        :func:`seed_kernels_identity`.

    Raises
    ------
    InvalidInputError
        An unreadable checkpoint, missing dataset or images not of a model's sensor size
        (all checked before any evaluation).
    """
    from ekdun.evaluation.tables import label_for

    device = resolve_device(device)   # an unavailable device is refused before any work
    from ekdun.nets.builder import network_from_checkpoint

    models = [(path, *network_from_checkpoint(path))
              for path in map(checkpoint_path, checkpoints)]
    datasets = []        # every run's pairs are checked before any evaluation
    for path, model, doc in models:
        dataset, note = evaluation_pairs(data, doc["metadata"].get("data") or {},
                                         include_training, channel_order)
        sensor = tuple(model.physics.sensor_shape)
        if tuple(dataset.image_shape[1:]) != sensor:
            raise InvalidInputError(f"{data}: pairs are {dataset.image_shape[1]}x"
                                    f"{dataset.image_shape[2]} but {path} expects "
                                    f"{sensor[0]}x{sensor[1]}")
        datasets.append((dataset, note))
    results = []
    for (path, model, doc), (dataset, note) in zip(models, datasets, strict=True):
        meta = doc["metadata"]
        training = meta.get("training") or {}
        # a study's settings (TrainOptions.study); older runs kept them in overrides, training
        study = {**meta.get("overrides", {}), **training, **(meta.get("study") or {})}
        schedule = meta.get("overrides", {}).get("schedule") or (
            meta.get("schedule") if meta["model"] == "ekdun" else None)
        row = evaluate_model(model, dataset, label_for(meta["model"], schedule), lpips, device,
                             optical_center=recorded_optical_center(meta))
        model.cpu()   # off the device again: the next run's peak memory is its own
        row.update({"checkpoint": str(path), "model": meta["model"], "schedule": schedule,
                    "epochs": meta.get("epoch"), "seed": meta.get("seed"),
                    # what sets a run apart from the paper's: a table must not pool these
                    "kernel_param": study.get("kernel_param", "free"),
                    "physics_weight": float(study.get("physics_weight") or 0.0),
                    "kernel_lr_scale": training.get("kernel_lr_scale"),
                    **seed_kernels_identity(doc),
                    "pairs": list(dataset.names), "pairs_note": note})
        results.append(row)
        if log is not None:
            zones = row["by_zone"] or {}
            by_zone = " / ".join(f"{zones[z]['psnr']:.2f}" for z in ZONE_NAMES if z in zones)
            log(f"{row['label']}: PSNR {row['psnr']:.2f} dB (centre / middle / edge "
                f"{by_zone}), SSIM {row['ssim']:.4f} ({note})")
    return results

