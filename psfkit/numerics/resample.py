"""Block binning by ``factor × factor`` blocks: :func:`bin_image` sums (photons, mask
weights), :func:`bin_mean` averages in float64 (intensities). Trailing rows/columns that do not
fill a block are dropped, or refused with ``exact=True``."""

from __future__ import annotations

import math

import numpy as np

from psfkit.errors import InvalidInputError


def _blocks(image: np.ndarray, factor: int, exact: bool) -> np.ndarray:
    """``(..., H, W)`` → ``(..., H // f, f, W // f, f)`` view of the whole blocks."""
    if factor < 1 or int(factor) != factor:
        raise InvalidInputError(f"binning factor must be a positive integer, got {factor!r}")
    factor = int(factor)
    *lead, h, w = image.shape
    if exact and (h % factor or w % factor):
        raise InvalidInputError(f"shape {image.shape} is not a multiple of {factor}")
    hh, ww = h // factor, w // factor
    return image[..., :hh * factor, :ww * factor].reshape(*lead, hh, factor, ww, factor)


def bin_image(image: np.ndarray, factor: int, exact: bool = False,
              dtype: type | np.dtype | None = None) -> np.ndarray:
    """Sum ``factor × factor`` blocks of the last two axes.

    Parameters
    ----------
    image : numpy.ndarray
        ``(..., H, W)``.
    factor : int
        Block size (px); 1 returns ``image`` itself.
    exact : bool
        Refuse ``H`` or ``W`` not a multiple of ``factor``.
    dtype : numpy dtype, optional
        Floating-point precision of the sums (default: the input's).

    Returns
    -------
    numpy.ndarray
        ``(..., H // factor, W // factor)``.
    """
    if factor == 1:
        return image if dtype is None else image.astype(dtype, copy=False)
    blocks = _blocks(image, factor, exact)
    if not np.issubdtype(blocks.dtype, np.floating) and dtype is None:
        return blocks.sum(axis=(-3, -1))      # integers and masks: numpy's promoted sum
    # Whole-array adds of strided slices, the columns of a block first (the contiguous
    # axis), then its rows: the same sequential sums as ``blocks.sum(axis=(-3, -1))``
    # (bit-identical), at about twice the speed.
    cols = blocks[..., 0].astype(dtype or blocks.dtype)
    for j in range(1, factor):
        cols += blocks[..., j]
    out = cols[..., 0, :].copy()
    for i in range(1, factor):
        out += cols[..., i, :]
    return out


def bin_mean(image: np.ndarray, factor: int, exact: bool = False) -> np.ndarray:
    """Average ``factor × factor`` blocks of the last two axes in float64: ``(..., H // factor,
    W // factor)`` (``image`` itself when ``factor`` is 1)."""
    if factor == 1:
        return image
    return _blocks(image, factor, exact).mean(axis=(-3, -1), dtype=np.float64)


def binning_factor(shape: tuple[int, ...], target: int) -> int:
    """Smallest integer factor that brings the largest of ``shape`` to at most ``target`` px
    (at least 1)."""
    return max(1, math.ceil(max(shape) / target))
