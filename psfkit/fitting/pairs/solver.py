r"""An exact, streaming least-squares solver for eigen-kernels from (scene, measurement) pairs.

Problem. For scenes ``x_i`` (scaled by per-pair factors ``s_i``) and measurements ``y_i``, the
kernels ``K`` of Eq. 7 (either convention, :mod:`psfkit.forward`) minimise

.. math::

    f(K) = \tfrac12\sum_i\lVert s_i B_i K - y_i\rVert^2 + \tfrac\lambda2\lVert K\rVert^2
           + \tfrac\mu2\sum_{k\ge1}\lVert K_k - K_0\rVert^2 ,
    \qquad B_i K = A_K x_i = \mathrm{crop}\big(\textstyle\sum_k \dots\big),

whose normal equations :math:`(\sum_i s_i^2 B_i^\top B_i + \lambda I + \mu D)K
= \sum_i s_i B_i^\top y_i` this module solves **to convergence** (the relative residual is
reported), streaming the pairs in batches so that memory does not grow with their number.

What is exact, and what only preconditions. On the linear-convolution grid
(:func:`~psfkit.forward.kernel_space.linear_convolution_grid`) the model before the crop is a
circular convolution. If the whole linear convolution were measured (no crop) and the kernels
lived on the whole grid, the normal operator would be block-diagonal in frequency:

- *source side* (``y = crop(Σ_k K_k ⊛ (W_k x))``): one ``K × K`` block per frequency and
  channel, :math:`G_{kl}(\omega) = \sum_i s_i^2\,\overline{\hat S_{ik}(\omega)}\hat
  S_{il}(\omega)` with :math:`\hat S_{ik}` the spectrum of the weighted scene ``W_k x_i``,
  and the least squares would be one closed-form ``K × K`` solve per frequency (checked
  by ``tests/psfkit/test_pairs_solver.py``);
- *sensor side* (``y = Σ_k W_k ⊙ crop(K_k ⊛ x)``) the weights multiply *after* the
  convolution, so even without the crop the operator couples frequencies: its exact
  normal operator is not per-frequency. Replacing :math:`W_k W_l` by its mean
  :math:`m_{kl}` over the sensor gives the blocks :math:`m_{kl}\sum_i s_i^2|\hat x_i|^2`,
  an approximation only.

The sensor crop (every real measurement) and the kernel window (``Hk × Wk`` on a larger grid)
break the frequency diagonal in both conventions: the kernel offset ``t`` is seen by only
``(H'−|t_v|)(W'−|t_u|)`` of the outputs, and the normal operator of the cropped problem is not
a function of ``t − t'`` alone, so it has no compact per-frequency form and cannot be summed over
the pairs once. It is therefore applied exactly, pair by pair (:class:`KernelSpaceOperator`:
one pass over the pairs per iteration, in batches), and the per-frequency blocks serve as the
preconditioner of conjugate gradients,

.. math::

    P = E^\top \mathcal F^{-1}\big[G(\omega) + \lambda I + \mu D\big]^{-1}\mathcal F E,

symmetric positive definite (``E`` embeds the kernel window in the grid; ``E^\top`` extracts
it), so preconditioned CG converges to the exact least-squares solution whatever the quality of
``P``; ``P`` only sets how fast: on the 64 × 64 virtual bench about half the iterations of a
scalar per-kernel preconditioner (research/notes/forward-model-studies.md).

Non-negativity (and a support) is imposed afterwards by projected Newton-CG
(:func:`psfkit.fitting.pairs.constraints.projected_newton`), the one
non-negative solver, warm-started from the converged unconstrained solution and with the same
streaming normal operator.

Library entry points: :class:`psfkit.fitting.pairs.batches.PairBatches` (the pairs, in
batches, with optional per-pair scales), :class:`psfkit.fitting.pairs.gram.FrequencyGram` (the
per-frequency blocks, one pass) and :func:`solve_normal_equations` (PCG to a tolerance). The
non-negative solve built on them, projected Newton-CG, is
:func:`psfkit.fitting.pairs.constraints.projected_newton`.
:func:`psfkit.fitting.pairs.fit.fit_pairs` and the research studies' operator oracle
(``research/oracles.py``) are built on them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.fitting.pairs.batches import MeasurementSource, PairBatches
from psfkit.fitting.pairs.gram import difference_matrix
from psfkit.forward.convolution import embed_kernel


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
    """Preconditioned conjugate gradients for ``N K = rhs``, per colour channel (independent
    problems), until ``‖rhs − N K‖ ≤ tolerance · ‖rhs‖`` in every channel.

    ``normal`` must be symmetric positive (semi-)definite per channel and ``precondition``
    symmetric positive definite (e.g. :meth:`FrequencyGram.preconditioner`); then the iterates
    converge to the least-squares solution and the reported residual is the true one (it is
    recomputed from ``normal`` at the end, not only the recursively updated one, unless
    ``true_residual`` is false: an inner solve whose residual nobody reads saves that pass).
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
    r"""``K ↦ (Σ_i s_i² B_iᵀB_i + λ I + μ D) K`` (absolute ``λ``, ``μ``), computed in the
    batches' precision and returned in the argument's (one pass over the pairs a call)."""
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
                  tikhonov: float = 0.0, difference: float = 0.0, relative: bool = True,
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
        ``(N, C, H', W')``, or ``(start, stop) → measurements`` made on the fly.
    tikhonov, difference : float
        ``λ`` and ``μ``; with ``relative`` they are multiples of the mean per-frequency
        scene power (the diagonal of the Gram blocks), as ``psfkit fit-pairs`` states them.
    start : Tensor, optional
        Warm start ``(K, C, Hk, Wk)``.
    tolerance, max_iterations
        Stop at this relative residual of the normal equations, or after so many iterations.

    Returns
    -------
    (Tensor, SolveInfo, dict)
        Kernels ``(K, C, Hk, Wk)`` in the batches' dtype, the solve's record, and
        ``{"lambda", "mu", "reference"}`` (the absolute regularisation weights used), with
        the system solved: ``"normal"``, ``"rhs"``, ``"precondition"``, ``"batches"``,
        ``"gram"``.
    """
    gram = batches.gram()
    reference = gram.reference_power()
    lam = tikhonov * reference if relative else tikhonov
    mu = difference * reference if relative else difference
    rhs = batches.rhs(measurements)
    normal = regularised_normal(batches, lam, mu)
    precondition = gram.preconditioner(lam, mu)
    kernels, info = solve_normal_equations(
        normal, rhs, precondition, start, tolerance, max_iterations, bar)
    return kernels, info, {"lambda": lam, "mu": mu, "reference": reference,
                           "normal": normal, "rhs": rhs, "precondition": precondition,
                           "batches": batches, "gram": gram}


__all__ = [
    "SolveInfo",
    "embed_kernel",
    "regularised_normal",
    "solve_kernels",
    "solve_normal_equations",
]
