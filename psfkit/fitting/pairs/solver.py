r"""An exact, streaming least-squares solver for eigen-kernels from (scene, measurement) pairs.

For scenes ``x_i`` scaled by per-pair factors ``s_i`` and measurements ``y_i``, the kernels
``K`` of Eq. 7 (either convention) minimise

.. math::

    f(K) = \tfrac12\sum_i\lVert s_i B_i K - y_i\rVert^2 + \tfrac\lambda2\lVert K\rVert^2
           + \tfrac\mu2\sum_{k\ge1}\lVert K_k - K_0\rVert^2 ,
    \qquad B_i K = A_K x_i,

whose normal equations :math:`(\sum_i s_i^2 B_i^\top B_i + \lambda I + \mu D)K
= \sum_i s_i B_i^\top y_i` are solved **to convergence**, streaming the pairs in batches.

Without the sensor crop and the kernel window the normal operator would be block-diagonal in
frequency: source side one ``K × K`` block per frequency and channel,
:math:`G_{kl}(\omega) = \sum_i s_i^2\,\overline{\hat S_{ik}(\omega)}\hat S_{il}(\omega)`
(``S_ik`` the weighted scene ``W_k x_i``); sensor side only approximately, with :math:`W_k W_l`
replaced by its mean :math:`m_{kl}`. The crop and window break that, so the normal operator is
applied exactly pair by pair (:class:`KernelSpaceOperator`) and the blocks only precondition CG,

.. math::

    P = E^\top \mathcal F^{-1}\big[G(\omega) + \lambda I + \mu D\big]^{-1}\mathcal F E,

symmetric positive definite (``E`` embeds the kernel window), so PCG converges to the exact
solution whatever ``P``'s quality. Non-negativity is imposed afterwards by
:func:`psfkit.fitting.pairs.constraints.projected_newton`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.fitting.grid.eigen import difference_matrix
from psfkit.fitting.pairs.batches import MeasurementSource, PairBatches


def _per_channel_dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(dim=(0, 2, 3))                                        # (C,)


@dataclass
class SolveInfo:
    """How a solve went: iterations, final relative residual of the normal equations (max over
    channels), passes over the pairs, and the residual history."""

    iterations: int
    relative_residual: float
    converged: bool
    history: list[float]

    def as_dict(self) -> dict[str, Any]:
        return {"method": "pcg-frequency-gram", "iterations": self.iterations,
                "relative_residual": self.relative_residual, "converged": self.converged}


def solve_normal_equations(normal: Callable[[Tensor], Tensor], rhs: Tensor,
                           precondition: Callable[[Tensor], Tensor],
                           start: Tensor | None = None, tolerance: float = 1e-6,
                           max_iterations: int = 500, bar: Any = None,
                           true_residual: bool = True) -> tuple[Tensor, SolveInfo]:
    """Preconditioned conjugate gradients for ``N K = rhs`` per colour channel, until
    ``‖rhs − N K‖ ≤ tolerance · ‖rhs‖`` in every channel.

    ``normal`` symmetric positive (semi-)definite per channel, ``precondition`` symmetric positive
    definite. The reported residual is recomputed from ``normal`` at the end unless
    ``true_residual`` is false.
    """
    x = torch.zeros_like(rhs) if start is None else start.clone()
    r = rhs - normal(x) if start is not None and bool(start.abs().max() > 0) else rhs.clone()
    norm_rhs = _per_channel_dot(rhs, rhs).sqrt().clamp_min(1e-300)
    relative = float((_per_channel_dot(r, r).sqrt() / norm_rhs).max())
    history = [relative]
    done = 0
    if relative > tolerance:
        z = precondition(r)
        p = z.clone()
        rz = _per_channel_dot(r, z)
        while done < max_iterations:
            done += 1
            ap = normal(p)
            curvature = _per_channel_dot(p, ap)
            alpha = torch.where(curvature > 0, rz / curvature.clamp_min(1e-300),
                                torch.zeros_like(rz))
            x += alpha[None, :, None, None] * p
            r -= alpha[None, :, None, None] * ap
            relative = float((_per_channel_dot(r, r).sqrt() / norm_rhs).max())
            history.append(relative)
            if bar is not None:
                bar.update(1)
            if relative < tolerance:
                break
            z = precondition(r)
            rz_new = _per_channel_dot(r, z)
            beta = rz_new / rz.clamp_min(1e-300)
            p = z + beta[None, :, None, None] * p
            rz = rz_new
        if true_residual:   # the recursion drifts in finite precision
            r = rhs - normal(x)
            relative = float((_per_channel_dot(r, r).sqrt() / norm_rhs).max())
            history.append(relative)
    return x, SolveInfo(iterations=done, relative_residual=relative,
                        converged=relative <= max(tolerance, 10 * tolerance) or done == 0,
                        history=history)


def regularised_normal(batches: PairBatches, tikhonov: float = 0.0, difference: float = 0.0
                       ) -> Callable[[Tensor], Tensor]:
    """``K ↦ (Σ_i s_i² B_iᵀB_i + λ I + μ D) K`` (absolute ``λ``, ``μ``), computed in the batches'
    precision and returned in the argument's (one pass over the pairs a call)."""
    k = batches.n_kernels
    prior = torch.as_tensor(difference_matrix(k), dtype=batches.dtype, device=batches.device)

    def normal(kernels: Tensor) -> Tensor:
        v = kernels.to(batches.dtype)
        out = batches.normal(v)
        if tikhonov:
            out = out + tikhonov * v
        if difference and k > 1:
            out = out + difference * torch.tensordot(prior, v, dims=([1], [0]))
        return out.to(kernels.dtype)

    return normal


def solve_kernels(batches: PairBatches,
                  measurements: np.ndarray | Tensor | MeasurementSource,
                  tikhonov: float = 0.0, difference: float = 0.0,
                  start: Tensor | None = None, tolerance: float = 1e-6,
                  max_iterations: int = 500, bar: Any = None
                  ) -> tuple[Tensor, SolveInfo, dict[str, Any]]:
    """Unconstrained least-squares kernels of ``batches`` against ``measurements``.

    Two passes for the Gram blocks and ``Bᵀy``, then one per CG iteration.

    Parameters
    ----------
    batches : PairBatches
        The scenes (and per-pair scales in ``batches.scales``).
    measurements : array or callable
        ``(N, C, H', W')``, or ``(start, stop) → measurements``.
    tikhonov, difference : float
        ``λ`` and ``μ``, multiples of the mean per-frequency scene power.
    start : Tensor, optional
        Warm start ``(K, C, Hk, Wk)``.
    tolerance, max_iterations
        Stop at this relative residual of the normal equations, or after so many iterations.

    Returns
    -------
    (Tensor, SolveInfo, dict)
        Kernels ``(K, C, Hk, Wk)`` in the batches' dtype, the solve's record, and the system:
        ``"lambda"``, ``"mu"``, ``"reference"``, ``"normal"``, ``"rhs"``, ``"precondition"``,
        ``"batches"``, ``"gram"``.
    """
    gram = batches.gram()
    reference = gram.reference_power()
    lam = tikhonov * reference
    mu = difference * reference
    rhs = batches.rhs(measurements)
    normal = regularised_normal(batches, lam, mu)
    precondition = gram.preconditioner(lam, mu)
    kernels, info = solve_normal_equations(
        normal, rhs, precondition, start, tolerance, max_iterations, bar)
    return kernels, info, {"lambda": lam, "mu": mu, "reference": reference,
                           "normal": normal, "rhs": rhs, "precondition": precondition,
                           "batches": batches, "gram": gram}
