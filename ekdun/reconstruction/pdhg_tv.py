r"""Total-variation reconstruction with any forward operator: PDHG (Chambolle–Pock).

For models whose normal operator ``AᵀA`` is not diagonal in Fourier space (the eigen-kernel
model of Eq. 7), ADMM's closed-form ``x`` update does not exist. The primal–dual hybrid
gradient method needs only ``A`` and its exact adjoint ``Aᵀ``:

.. math::

    \min_x\ \tfrac12 \lVert A x - y\rVert_2^2 + \lambda \lVert \nabla x\rVert_1
           \;[+\ \iota_{x \ge 0}(x)]

with ``x`` the scene on the sensor's grid ``(C, H', W')`` and ``∇`` circular forward
differences (anisotropic TV, as in :mod:`ekdun.models.tv_admm_steps`). Scale-free
parametrisation: the measurement is divided by its peak and the operator by its norm
``‖A‖`` (:func:`psfkit.forward.norm.operator_norm`, power iteration on the operator itself,
crop included), so ``tv`` means the same for any model and units, and the same objective as
the ADMM solvers' (:mod:`ekdun.reconstruction.ek_admm`, which use the same estimate). In those
units ``K = [A/‖A‖; ∇/√8]`` has norm ``≤ √(1.05² + 1)`` (the estimate is from below; 5 %
margin) and the steps ``σ = t = 0.99/√(1.05² + 1)`` satisfy ``σ t ‖K‖² < 1`` (Chambolle & Pock
2011, Algorithm 1, θ = 1)::

    p ← (p + σ(A x̄ − y)) / (1 + σ)            prox of the data term's conjugate
    q ← clip(q + σ ∇x̄/√8, ±√8·tv)              prox of the TV term's conjugate
    x⁺ ← x − t(Aᵀp + ∇ᵀq/√8)  [then max(·, 0)]
    x̄ ← 2x⁺ − x

One iteration costs one ``A`` and one ``Aᵀ`` (SI: 2 FFTs each; EK with K kernels: 1 + K).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, TensorShapeError
from ekdun.models.tv_admm_steps import finite_differences, finite_differences_adjoint
from ekdun.physics.operators import PreparedOperator
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from psfkit.forward.norm import operator_norm

Operator = PreparedOperator | ExtendedSceneOperator

_TV_NORM = math.sqrt(8.0)     # ‖∇‖ bound of the 2-D forward differences
_STEP_MARGIN = 1.05           # the step sizes allow ‖A‖ up to 5 % above its estimate


@dataclass
class TVResult:
    """Result of :func:`pdhg_tv`.

    Attributes
    ----------
    image : Tensor
        ``(C, H', W')`` (or padded-grid) reconstruction in the units of ``x`` in ``y = A x``.
    iterations : int
        Iterations run.
    converged : bool
        Whether the relative-change rule stopped it (``tol > 0``).
    relative_change : list of float
        ``‖x_k − x_{k−1}‖ / ‖x_k‖`` per iteration (:func:`ek_admm_tv` records it only with a
        ``tol`` or a callback).
    objective : list of float
        The objective after each iteration (only with ``track_objective``).
    operator_norm : float
        The ``‖A‖`` used.
    """

    image: Tensor
    iterations: int
    converged: bool
    relative_change: list[float] = field(default_factory=list)
    objective: list[float] = field(default_factory=list)
    operator_norm: float = 1.0


def tv_objective(op: Operator, x: Tensor, y: Tensor, weight: float) -> float:
    """``½‖A x − y‖² + weight·‖∇x‖₁`` for ``x`` ``(1, C, ...)`` and ``y`` ``(1, C, H', W')``."""
    r = op.A(x) - y
    return float(0.5 * (r * r).sum() + weight * finite_differences(x).abs().sum())


def pdhg_tv(measurement: Tensor, op: Operator, tv: float = 1e-3,
            iterations: int = 300, nonneg: bool = False, tol: float = 0.0,
            norm: float | None = None, track_objective: bool = False,
            callback: Callable[[int, float], None] | None = None) -> TVResult:
    """TV-regularised least squares with PDHG for any operator with an exact adjoint.

    Parameters
    ----------
    measurement : Tensor
        ``(C, H', W')`` in the operator's dtype and device.
    op : PreparedOperator or ExtendedSceneOperator
        ``A`` and ``Aᵀ`` (e.g. ``EigenKernelOperator(...).prepare()``, scene ``(C, H', W')``,
        or :class:`~ekdun.reconstruction.extended_scene.ExtendedSceneOperator`, scene on the
        padded grid).
    tv : float
        TV weight, relative (see the module docstring): the objective's ``λ`` is
        ``tv · peak(|y|) · ‖A‖``.
    iterations : int
        Maximum iterations.
    nonneg : bool
        Constrain the image to ``x >= 0``.
    tol : float
        Stop once the relative change ``‖x_k − x_{k−1}‖/‖x_k‖`` falls below ``tol``
        (0: run all ``iterations``).
    norm : float, optional
        ``‖A‖`` if known (default :func:`psfkit.forward.norm.operator_norm`, cached on
        ``op``); sets the units of ``tv``.
    track_objective : bool
        Record the objective every iteration (one more ``A`` per iteration).
    callback : callable, optional
        ``callback(iteration, relative_change)`` after each iteration (progress bars).

    Returns
    -------
    TVResult

    Raises
    ------
    ConfigurationError
        Negative ``tv`` or ``tol``, ``iterations < 1``.
    TensorShapeError
        A measurement that does not fit the operator.
    """
    if tv < 0 or tol < 0 or iterations < 1:
        raise ConfigurationError(f"need tv >= 0, tol >= 0 and iterations >= 1 (got tv={tv}, "
                                 f"tol={tol}, iterations={iterations})")
    if measurement.ndim != 3:
        raise TensorShapeError(f"measurement must be (C, H, W), got {tuple(measurement.shape)}")
    y = measurement[None]
    op.check(y, "measurement")
    peak = float(y.abs().max().clamp_min(1e-30))
    if norm is None:
        norm = operator_norm(op)                        # the one estimate, cached on op
    y_n = y / peak                                      # peak 1
    scene = op.A_adjoint(y_n)                           # the scene's shape (sensor or grid)
    scale_a = 1.0 / norm                                # A' = A/‖A‖, ‖A'‖ ≈ 1
    # the estimate approaches ‖A‖ from below: steps for ‖A'‖ <= 1.05 keep σ t ‖K‖² < 1
    step = 0.99 / math.sqrt(_STEP_MARGIN ** 2 + 1.0)
    bound = tv * _TV_NORM
    x = torch.zeros_like(scene)
    x_bar = x
    p = torch.zeros_like(y_n)
    q = torch.zeros((2, *x.shape), dtype=y.dtype, device=y.device)
    result = TVResult(image=x[0], iterations=0, converged=False, operator_norm=norm)
    weight = tv * peak * norm
    for k in range(1, iterations + 1):
        p = (p + step * (scale_a * op.A(x_bar) - y_n)) / (1.0 + step)
        q = (q + (step / _TV_NORM) * finite_differences(x_bar)).clamp(-bound, bound)
        x_new = x - step * (scale_a * op.A_adjoint(p) + finite_differences_adjoint(q) / _TV_NORM)
        if nonneg:
            x_new = x_new.clamp_min(0)
        change = float((x_new - x).norm() / (x_new.norm().clamp_min(1e-30)))
        x_bar = 2 * x_new - x
        x = x_new
        result.relative_change.append(change)
        result.iterations = k
        if track_objective:
            result.objective.append(tv_objective(op, x * (peak / norm), y, weight))
        if callback is not None:
            callback(k, change)
        if tol > 0 and change < tol:
            result.converged = True
            break
    # Back to the units of y = A x: x = x' · peak / ‖A‖.
    result.image = (x * (peak / norm))[0]
    return result
