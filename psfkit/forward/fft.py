"""The two FFT entry points of the forward model, and a counter of their calls.

Every 2-D FFT goes through :func:`rfft2` and every inverse through :func:`irfft2`, so the FFT
count of any algorithm can be audited::

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
    """Calls of :func:`rfft2` (``forward``) and :func:`irfft2` (``inverse``)."""

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
    """Count the calls of :func:`rfft2` / :func:`irfft2` inside the ``with`` block.

    Blocks may nest. Not thread-safe: other threads' calls are counted too.
    """
    count = FFTCount()
    _ACTIVE.append(count)
    try:
        yield count
    finally:
        _ACTIVE.remove(count)


def rfft2(z: Tensor, grid_shape: tuple[int, int] | None = None) -> Tensor:
    """Real 2-D FFT over the last two axes of ``z`` ``(..., h, w)``.

    With ``grid_shape`` ``(PH, PW)`` the input is zero-padded at the end of each axis inside the
    FFT call. Returns the ``(..., PH, PW//2 + 1)`` complex half spectrum.
    """
    for count in _ACTIVE:
        count.forward += 1
    return torch.fft.rfft2(z) if grid_shape is None else torch.fft.rfft2(z, s=grid_shape)


def irfft2(spectrum: Tensor, grid_shape: tuple[int, int],
           crop_shape: tuple[int, int] | None = None,
           start: tuple[int, int] = (0, 0)) -> Tensor:
    """Inverse of :func:`rfft2` on a ``grid_shape`` ``(PH, PW)`` grid (odd widths need it).

    With ``crop_shape`` ``(h, w)`` only that block at ``start`` ``(row, column)`` (modulo the
    grid, wrapping around it) is computed: the row inverse runs only on the rows kept (the same
    numbers as slicing the full inverse). Returns ``(..., PH, PW)`` or ``(..., h, w)`` real.
    """
    for count in _ACTIVE:
        count.inverse += 1
    if crop_shape is None:
        return torch.fft.irfft2(spectrum, s=grid_shape)
    columns = wrapped_slice(torch.fft.ifft(spectrum, dim=-2), start[0], crop_shape[0], -2)
    rows = torch.fft.irfft(columns, n=grid_shape[1], dim=-1)
    return wrapped_slice(rows, start[1], crop_shape[1], -1)


def wrapped_slice(z: Tensor, first: int, size: int, dim: int) -> Tensor:
    """``size`` entries of ``z`` along ``dim`` from ``first`` (modulo the axis), wrapping around the
    end: a view when they do not wrap, else one copy."""
    first %= z.shape[dim]
    if first + size <= z.shape[dim]:
        return z.narrow(dim, first, size)
    return torch.cat([z.narrow(dim, first, z.shape[dim] - first),
                      z.narrow(dim, 0, first + size - z.shape[dim])], dim=dim)
