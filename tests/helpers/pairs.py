"""The relative KKT residual of a non-negative least-squares fit, evaluated from scratch."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from psfkit.fitting.pairs.constraints import _natural_residual, lipschitz_constant


def kkt_residual(normal: Callable[[Tensor], Tensor], rhs: Tensor, kernels: Tensor,
                 support: Tensor | None = None, lipschitz: Tensor | None = None) -> Tensor:
    r"""Per-channel relative natural residual of ``min ½KᵀNK − rhsᵀK`` over ``K ≥ 0`` (and
    ``K = 0`` outside ``support``), ``(C,)``: what
    :func:`psfkit.fitting.pairs.constraints.projected_newton` records as ``kkt_residual`` (``L``
    from :func:`~psfkit.fitting.pairs.constraints.lipschitz_constant` when not given)."""
    if lipschitz is None:
        lipschitz = lipschitz_constant(normal, kernels)
    return _natural_residual(kernels, normal(kernels) - rhs, lipschitz, support)
