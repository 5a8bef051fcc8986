"""The two FFT entry points of the forward model, and a counter of their calls.

Every 2-D FFT of the forward model (operators, kernel fits, ADMM-TV, Le-ADMM-U, the dense
virtual-bench model) goes through :func:`rfft2` and every inverse through :func:`irfft2`, so the
FFT count of any algorithm can be audited with :func:`count_ffts` (tests and
``benchmarks/bench_ekdun_operators.py`` do)::

    with count_ffts() as n:
        op.A(x)
    assert (n.forward, n.inverse) == (1, 3)
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class FFTCount:
    """Calls of :func:`rfft2` (``forward``) and :func:`irfft2` (``inverse``) seen so far.

    Each call transforms every leading plane of its input at once and counts once.
    """

    forward: int = 0
    inverse: int = 0

    def as_tuple(self) -> tuple[int, int]:
        """``(forward, inverse)``."""
        return (self.forward, self.inverse)

    def take(self) -> tuple[int, int]:
        """``(forward, inverse)`` counted since the last :meth:`take`, then reset to zero."""
        counts = self.as_tuple()
        self.forward = self.inverse = 0
        return counts


# The counters of the active count_ffts() blocks (usually none: one empty-list check per FFT).
_ACTIVE: list[FFTCount] = []


@contextmanager
def count_ffts() -> Iterator[FFTCount]:
    """Count the calls of :func:`rfft2` / :func:`irfft2` made inside the ``with`` block.

    Blocks may nest (each counts its own calls). Not thread-safe: counts from other threads
    running at the same time are included.
    """
    count = FFTCount()
    _ACTIVE.append(count)
    try:
        yield count
    finally:
        _ACTIVE.remove(count)


def rfft2(z: Tensor, grid_shape: tuple[int, int] | None = None) -> Tensor:
    """Real 2-D FFT over the last two axes (the one place forward FFTs are taken).

    With ``grid_shape``, ``z`` is zero-padded at the end of each axis to that size first (inside
    the FFT call: no explicit padded copy).

    Parameters
    ----------
    z : Tensor
        ``(..., h, w)`` real.
    grid_shape : (int, int), optional
        ``(PH, PW)`` with ``PH >= h``, ``PW >= w``.

    Returns
    -------
    Tensor
        ``(..., PH, PW//2 + 1)`` complex half spectrum.
    """
    for count in _ACTIVE:
        count.forward += 1
    return torch.fft.rfft2(z) if grid_shape is None else torch.fft.rfft2(z, s=grid_shape)


def irfft2(spectrum: Tensor, grid_shape: tuple[int, int],
           crop_shape: tuple[int, int] | None = None,
           start: tuple[int, int] = (0, 0)) -> Tensor:
    """Inverse of :func:`rfft2` on a ``grid_shape`` grid (the one place inverse FFTs are taken).

    ``grid_shape`` is needed because the half spectrum does not tell odd from even widths.
    With ``crop_shape`` only the ``crop_shape`` block at ``start`` is returned, and only
    computed: the complex inverse along the columns runs on the whole grid, but the real
    inverse along the rows only on the rows kept (the same numbers as ``irfft2`` then slicing,
    for about three quarters of the work).

    Parameters
    ----------
    spectrum : Tensor
        ``(..., PH, PW//2 + 1)`` complex.
    grid_shape : (int, int)
        ``(PH, PW)``.
    crop_shape : (int, int), optional
        ``(h, w)`` block to keep.
    start : (int, int)
        ``(row, column)`` of the block's first pixel, taken modulo the grid: the block wraps
        around it (a kernel centred on the origin has ``start = (−Hk//2, −Wk//2)``).

    Returns
    -------
    Tensor
        ``(..., PH, PW)`` real, or ``(..., h, w)`` with ``crop_shape``.
    """
    for count in _ACTIVE:
        count.inverse += 1
    if crop_shape is None:
        return torch.fft.irfft2(spectrum, s=grid_shape)
    columns = wrapped_slice(torch.fft.ifft(spectrum, dim=-2), start[0], crop_shape[0], -2)
    rows = torch.fft.irfft(columns, n=grid_shape[1], dim=-1)
    return wrapped_slice(rows, start[1], crop_shape[1], -1)


def wrapped_slice(z: Tensor, first: int, size: int, dim: int) -> Tensor:
    """``size`` entries of ``z`` along ``dim`` from index ``first`` (modulo the axis),
    wrapping around the end: a view when they do not wrap, else one copy (the blocks of
    :func:`irfft2` and the kernel window of :func:`psfkit.forward.convolution.extract_kernel`)."""
    first %= z.shape[dim]
    if first + size <= z.shape[dim]:
        return z.narrow(dim, first, size)
    return torch.cat([z.narrow(dim, first, z.shape[dim] - first),
                      z.narrow(dim, 0, first + size - z.shape[dim])], dim=dim)
