"""The base class of every linear operator of the forward model (deepinv's ``LinearPhysics``).

A subclass defines ``A``, its exact adjoint ``A_adjoint`` and their shapes, and gets
:meth:`~LinearOperator.norm` (``‖A‖`` by power iteration on ``AᵀA`` as applied, cached).
"""

from __future__ import annotations

import torch
from torch import Tensor

from psfkit.forward.norm import NORM_MAX_ITERATIONS, NORM_TOLERANCE, operator_norm


class LinearOperator:
    """``A`` and ``Aᵀ`` with their norm.

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
