"""The base class of every linear operator of the forward model (deepinv's ``LinearPhysics``).

A subclass defines ``A``, its exact adjoint ``A_adjoint`` and their shapes, and gets
:meth:`~LinearOperator.norm` (``‖A‖`` by power iteration on ``AᵀA`` as applied, cached) and
:meth:`~LinearOperator.adjointness_error` (the dot-product test every operator's tests run).
"""

from __future__ import annotations

import torch
from torch import Tensor

from psfkit.forward.norm import NORM_MAX_ITERATIONS, NORM_TOLERANCE, operator_norm


class LinearOperator:
    """``A`` and ``Aᵀ`` with their norm and their adjointness test.

    Subclasses set ``dtype`` and ``device``, define :meth:`A` and :meth:`A_adjoint`, and
    :meth:`domain_shape` unless their input is a sensor-sized scene (``channels``,
    ``sensor_shape``).
    """

    dtype: torch.dtype
    device: torch.device | str | None = None

    def A(self, x: Tensor) -> Tensor:
        """``y = A x``."""
        raise NotImplementedError

    def A_adjoint(self, y: Tensor) -> Tensor:
        """``x = Aᵀ y``, the exact adjoint of :meth:`A`."""
        raise NotImplementedError

    def domain_shape(self) -> tuple[int, ...]:
        """Shape of one input of :meth:`A`; default ``(1, C, H', W')``."""
        return (1, int(self.channels), *self.sensor_shape)  # type: ignore[attr-defined]

    def norm(self, tol: float = NORM_TOLERANCE, max_iterations: int = NORM_MAX_ITERATIONS,
             seed: int = 0) -> float:
        """``‖A‖`` within about ``tol``, from below (:func:`psfkit.forward.norm.operator_norm`)."""
        return operator_norm(self, self.domain_shape(), self.dtype, tol, max_iterations, seed)

    def adjointness_error(self, seed: int = 0) -> float:
        r"""Relative error of ``⟨A x, y⟩ = ⟨x, Aᵀ y⟩`` on seeded random ``x`` and ``y``,

        .. math::

            \frac{|\langle A x, y\rangle - \langle x, A^\top y\rangle|}
                 {\max(\lVert A x\rVert\,\lVert y\rVert,\ \lVert x\rVert\,\lVert A^\top y\rVert)}

        (sums in float64): about the working precision's rounding for an exact adjoint (1e-7 in
        float32, 1e-16 in float64), of order 1 for a wrong one."""
        generator = torch.Generator().manual_seed(seed)

        def draw(shape: tuple[int, ...]) -> Tensor:
            t = torch.randn(shape, generator=generator, dtype=torch.float64)
            return t.to(dtype=self.dtype, device=self.device)

        x = draw(self.domain_shape())
        with torch.no_grad():
            ax = self.A(x)
            y = draw(tuple(ax.shape))
            ax, aty = ax.double(), self.A_adjoint(y).double()
        x, y = x.double(), y.double()
        gap = abs(float((ax * y).sum()) - float((x * aty).sum()))
        scale = max(float(ax.norm() * y.norm()), float(x.norm() * aty.norm()))
        return gap / scale if scale > 0 else gap
