"""What only the tests use of the forward model: the dot-product test of an operator's adjoint,
and :func:`extract_kernel`, the adjoint of :func:`psfkit.forward.convolution.embed_kernel`."""

from __future__ import annotations

import torch
from torch import Tensor

from psfkit.forward.fft import wrapped_slice
from psfkit.forward.geometry import kernel_origin


def adjointness_error(op, seed: int = 0) -> float:  # type: ignore[no-untyped-def]
    r"""Relative error of ``⟨A x, y⟩ = ⟨x, Aᵀ y⟩`` on seeded random ``x`` and ``y``,

    .. math::

        \frac{|\langle A x, y\rangle - \langle x, A^\top y\rangle|}
             {\max(\lVert A x\rVert\,\lVert y\rVert,\ \lVert x\rVert\,\lVert A^\top y\rVert)}

    (sums in float64) of a :class:`~psfkit.forward.base.LinearOperator` ``op``: about the
    working precision's rounding for an exact adjoint (1e-7 in float32, 1e-16 in float64), of
    order 1 for a wrong one."""
    generator = torch.Generator().manual_seed(seed)

    def draw(shape: tuple[int, ...]) -> Tensor:
        t = torch.randn(shape, generator=generator, dtype=torch.float64)
        return t.to(dtype=op.dtype, device=op.device)

    x = draw(op.domain_shape())
    with torch.no_grad():
        ax = op.A(x)
        y = draw(tuple(ax.shape))
        ax, aty = ax.double(), op.A_adjoint(y).double()
    x, y = x.double(), y.double()
    gap = abs(float((ax * y).sum()) - float((x * aty).sum()))
    scale = max(float(ax.norm() * y.norm()), float(x.norm() * aty.norm()))
    return gap / scale if scale > 0 else gap


def extract_kernel(full: Tensor, kernel_shape: tuple[int, int]) -> Tensor:
    """Adjoint of :func:`~psfkit.forward.convolution.embed_kernel`: the centred ``(..., Hk, Wk)``
    window of ``full``."""
    row, col = kernel_origin(kernel_shape)
    rows = wrapped_slice(full, -row, kernel_shape[0], -2)
    return wrapped_slice(rows, -col, kernel_shape[1], -1)
