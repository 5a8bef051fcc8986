r"""``‖A‖`` of a forward operator, estimated once: power iteration on the actual operator.

The TV weight of every solver is relative to ``‖A‖`` (ADMM, PDHG), and the constrained kernel
fit of ``psfkit fit-pairs`` and the unrolled networks take their step sizes from the largest
eigenvalue of a normal operator. All of them call this module, so that ``--tv`` means one
objective whatever the solver.

The crop to the sensor lowers the norm below the kernels' spectral gain
``max_ω |K̂(ω)|`` (the norm of the circular convolution on the padded grid): on the DLMD
shift-invariant model 0.486 against 0.624. So the estimate is taken on the operator as it is,
crop included:

.. math::

    \lambda_{n} = \lVert N v_n\rVert, \qquad v_{n+1} = N v_n / \lVert N v_n\rVert,
    \qquad N = A^\top A,

from a fixed random start (``seed``: deterministic), stopped once both the relative change
``Δ_n`` of ``√λ`` between iterations and the remaining error extrapolated from the geometric
rate of those changes (``Δ_n ρ/(1 − ρ)``, ``ρ`` the largest of the last three
``Δ_n/Δ_{n−1}``) fall below ``tol``, after at least ``MIN_ITERATIONS`` (or at
``max_iterations``): the estimate of ``‖A‖`` is then within about ``tol`` (relative; checked
against a dense SVD in ``tests/psfkit/test_forward.py``). For a symmetric positive
semi-definite ``N`` the estimate approaches the largest eigenvalue from below;
callers that need an upper bound for a step size add their own margin.

:func:`operator_norm` caches its result on the operator object (keyed by the scene shape,
dtype and tolerance), so a model built once is measured once. :func:`spectral_bound` is the
cheap bound from above that the unrolled networks use to initialise their step sizes.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from typing import Any, Protocol

import torch
from torch import Tensor

#: Default relative accuracy of the ``‖A‖`` estimate.
NORM_TOLERANCE = 1e-3
#: Iterations always run (see :func:`_settled`).
MIN_ITERATIONS = 20
#: Default iteration cap.
NORM_MAX_ITERATIONS = 300


class OperatorLike(Protocol):
    """Anything with ``A`` and its exact adjoint ``A_adjoint`` (deepinv's physics interface)."""

    def A(self, x: Tensor) -> Tensor: ...

    def A_adjoint(self, y: Tensor) -> Tensor: ...


def largest_eigenvalue(normal: Callable[[Tensor], Tensor], shape: tuple[int, ...],
                       dtype: torch.dtype, device: torch.device | str | None = None,
                       block_dim: int | None = None, tol: float = NORM_TOLERANCE,
                       max_iterations: int = NORM_MAX_ITERATIONS, seed: int = 0) -> Tensor:
    """Largest eigenvalue of a symmetric positive semi-definite operator, by power iteration.

    Parameters
    ----------
    normal : callable
        ``v ↦ N v`` on arrays of ``shape``.
    shape : tuple of int
        Shape of ``N``'s input.
    dtype, device
        Of the iterate.
    block_dim : int, optional
        An axis along which ``N`` is block-diagonal (the colour channels of the kernel fit's
        normal operator): one eigenvalue per index along it, each from its own normalisation.
    tol : float
        Relative accuracy of ``sqrt`` of the estimates (see the module docstring).
    max_iterations : int
        Iteration cap.
    seed : int
        Seed of the uniform random start (the same estimate on every call).

    Returns
    -------
    Tensor
        Scalar, or ``(shape[block_dim],)`` with ``block_dim``; float64 on the CPU.
    """
    if max_iterations < 1 or tol < 0:
        raise ValueError(f"need max_iterations >= 1 and tol >= 0, got {max_iterations}, {tol}")
    generator = torch.Generator(device="cpu").manual_seed(seed)
    # a positive start overlaps the top singular vector of a non-negative PSF's operator
    v = torch.rand(shape, generator=generator, dtype=torch.float64).to(dtype=dtype,
                                                                         device=device)
    dims = (tuple(d for d in range(len(shape)) if d != block_dim % len(shape))
            if block_dim is not None else tuple(range(len(shape))))

    def norms(t: Tensor) -> Tensor:
        n = t.double().pow(2).sum(dim=dims).sqrt()
        return n if block_dim is None else n.reshape(
            [-1 if d == block_dim % len(shape) else 1 for d in range(len(shape))])

    v = v / norms(v).clamp_min(1e-300).to(dtype)
    estimate = torch.zeros(())
    changes: list[float] = []
    for _ in range(max_iterations):
        w = normal(v)
        size = norms(w)
        new = size.flatten().cpu()
        changes.append(float(((new.sqrt() - estimate.sqrt()).abs()
                              / new.sqrt().clamp_min(1e-300)).max()))
        estimate = new
        v = w / size.clamp_min(1e-300).to(w.dtype)
        if _settled(changes, tol):
            break
    return estimate if block_dim is not None else estimate.reshape(())


def spectral_bound(spectra: Tensor) -> float:
    """``max_{k,c,ω} |K̂_k(ω)|``: the norm of the largest kernel's circular convolution on the
    padded grid, an upper bound of ``‖A‖`` for one kernel (crop and pad have norm 1).

    Not ``‖A‖``: the crop lowers it (DLMD SI: 0.624 against 0.486; use
    :func:`operator_norm`). The unrolled networks scale their initial step sizes with it,
    which wants a bound from above that needs no iteration.

    Parameters
    ----------
    spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` complex kernel spectra.
    """
    return float(spectra.abs().amax())


def _settled(changes: list[float], tol: float) -> bool:
    """Whether the power iteration is within ``tol`` of its limit.

    The estimate converges geometrically; the rate is read off the last changes,
    ``ρ = max Δ_n/Δ_{n−1}`` over the last three (the first iterations decay faster, as the
    other components die out, and would promise too much), and what is left is about
    ``Δ_n ρ/(1 − ρ)``. A small change alone may only mean slow convergence. No rule read off
    the iterates can see a second singular value within a few percent of the first whose
    component is still small (its decay has not started to dominate): hence at least
    ``MIN_ITERATIONS``.
    """
    if len(changes) < MIN_ITERATIONS:
        return False
    last = changes[-4:]
    rho = max(b / a if a > 0 else 0.0 for a, b in itertools.pairwise(last))
    return rho < 1 and changes[-1] * rho / (1 - rho) < tol and changes[-1] < tol


def _scene_shape(op: Any) -> tuple[int, ...]:
    """``(1, C, H, W)`` of the operator's scene: the padded grid for an extended-scene
    operator, the sensor otherwise."""
    grid = getattr(op, "scene_shape", None)
    if grid is not None:
        return (1, int(op.channels), *grid)
    return (1, int(op.channels), *op.sensor_shape)


def operator_norm(op: OperatorLike, shape: tuple[int, ...] | None = None,
                  dtype: torch.dtype | None = None, tol: float = NORM_TOLERANCE,
                  max_iterations: int = NORM_MAX_ITERATIONS, seed: int = 0) -> float:
    """``‖A‖`` (largest singular value) of ``op`` by power iteration on ``AᵀA``, cached on ``op``.

    Parameters
    ----------
    op : object with ``A`` and ``A_adjoint``
        The operator exactly as the solver applies it (crop included).
    shape : tuple of int, optional
        Scene shape ``(B, C, H, W)`` (default: ``op.scene_shape`` on the padded grid when the
        operator has one, else ``op.sensor_shape``, with ``op.channels`` and ``B = 1``).
    dtype : torch.dtype, optional
        Default ``op.dtype``.
    tol, max_iterations, seed
        As :func:`largest_eigenvalue` (the result is within about ``tol`` of its limit, and
        below ``‖A‖``).

    Returns
    -------
    float
        The estimate of ``‖A‖`` (in the operator's units).
    """
    shape = tuple(shape) if shape is not None else _scene_shape(op)
    dtype = dtype or op.dtype
    key = (shape, dtype, tol, max_iterations, seed)
    cache: dict = op.__dict__.setdefault("_operator_norm_cache", {})
    if key not in cache:
        device = getattr(op, "device", None)
        with torch.no_grad():
            value = largest_eigenvalue(lambda v: op.A_adjoint(op.A(v)), shape, dtype, device,
                                       tol=tol, max_iterations=max_iterations, seed=seed)
        cache[key] = math.sqrt(float(value))
    return cache[key]
