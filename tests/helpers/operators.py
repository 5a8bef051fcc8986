"""What only the tests use of the forward model: :func:`extract_kernel`, the adjoint of
:func:`psfkit.forward.convolution.embed_kernel`."""

from __future__ import annotations

from torch import Tensor

from psfkit.forward.fft import wrapped_slice
from psfkit.forward.geometry import kernel_origin


def extract_kernel(full: Tensor, kernel_shape: tuple[int, int]) -> Tensor:
    """Adjoint of :func:`~psfkit.forward.convolution.embed_kernel`: the centred ``(..., Hk, Wk)``
    window of ``full``."""
    row, col = kernel_origin(kernel_shape)
    rows = wrapped_slice(full, -row, kernel_shape[0], -2)
    return wrapped_slice(rows, -col, kernel_shape[1], -1)
