"""Between pixel grids: pairs binned for a cheaper fit (:func:`downsample_pairs`), and kernels
fitted to binned pairs brought back to the unbinned grid (:func:`upsampled_kernels`, a warm
start of the full-resolution fit)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from psfkit.errors import InvalidInputError
from psfkit.io.validation import MIN_PAIR_SIDE
from psfkit.numerics.resample import bin_mean


def downsample_pairs(scenes: np.ndarray, measurements: np.ndarray, factor: int,
                     where: str = "pairs") -> tuple[np.ndarray, np.ndarray]:
    """Average ``factor × factor`` blocks of ``(N, C, H, W)`` scenes and measurements (trailing
    rows/columns dropped).

    Pairs under ``MIN_PAIR_SIDE`` px a side once binned are refused (``where`` names them).
    """
    h, w = scenes.shape[-2:]
    if h // factor < MIN_PAIR_SIDE or w // factor < MIN_PAIR_SIDE:
        binning = f" binned by --downsample {factor} to {h // factor}x{w // factor}" \
            if factor > 1 else ""
        raise InvalidInputError(f"{where}: {h}x{w} px pairs{binning} leave too few pixels "
                                f"to fit or evaluate a model (at least {MIN_PAIR_SIDE}x"
                                f"{MIN_PAIR_SIDE})")
    if factor == 1:
        return scenes, measurements
    return (bin_mean(scenes, factor).astype(np.float32),
            bin_mean(measurements, factor).astype(np.float32))


def upsampled_kernels(coarse: Tensor, factor: int, shape: tuple[int, int]) -> Tensor:
    """Kernels fitted to pairs binned ``factor`` times on the unbinned grid ``shape`` (a warm
    start): each binned pixel spread over its block, origin at the centre."""
    fine = coarse.repeat_interleave(factor, -2).repeat_interleave(factor, -1) / factor**2
    out = fine.new_zeros((*fine.shape[:-2], *shape))
    h, w = min(shape[0], fine.shape[-2]), min(shape[1], fine.shape[-1])
    out[..., :h, :w] = fine[..., :h, :w]
    shifts = tuple(n // 2 - factor * (c // 2) - factor // 2
                   for n, c in zip(shape, coarse.shape[-2:], strict=True))
    return torch.roll(out, shifts, dims=(-2, -1))
