r"""``‖A‖`` of a forward operator, estimated once: power iteration on the actual operator.

Every solver's TV weight is relative to ``‖A‖`` and the kernel fit and unrolled networks take
step sizes from the largest eigenvalue of a normal operator, all from here. The crop lowers
the norm below the spectral gain ``max_ω |K̂(ω)|`` (DLMD SI: 0.486 against 0.624), so it is
estimated on the operator as applied:

.. math::

    \lambda_{n} = \lVert N v_n\rVert, \qquad v_{n+1} = N v_n / \lVert N v_n\rVert,
    \qquad N = A^\top A,

from a seeded random start, stopped once the relative change ``Δ_n`` of ``√λ`` and the
extrapolated remaining error ``Δ_n ρ/(1 − ρ)`` (``ρ`` the largest of the last three
``Δ_n/Δ_{n−1}``) are below ``tol``, after at least ``MIN_ITERATIONS``. The estimate approaches
``‖A‖`` from below. :func:`operator_norm` caches on the operator; :func:`spectral_bound` is the
cheap upper bound for the networks' initial step sizes.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from typing import Protocol

import torch
from torch import Tensor

#: Default relative accuracy of the ``‖A‖`` estimate.
NORM_TOLERANCE = 1e-3
#: Iterations always run (see :func:`_settled`).
MIN_ITERATIONS = 20
#: Default iteration cap.
NORM_MAX_ITERATIONS = 300


class OperatorLike(Protocol):
    """Anything with ``A``, its exact adjoint ``A_adjoint`` and ``A``'s input shape."""

    def A(self, x: Tensor) -> Tensor: ...

    def domain_shape(self) -> tuple[int, ...]: ...

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
        ``N``'s input shape.
    dtype, device
        Of the iterate.
    block_dim : int, optional
        An axis along which ``N`` is block-diagonal: one eigenvalue per index along it.
    tol : float
        Relative accuracy of the estimate's ``sqrt`` (module docstring).
    max_iterations : int
    seed : int
        Seed of the uniform random start.

    Returns
    -------
    Tensor
        Scalar, or ``(shape[block_dim],)``; float64 on the CPU.
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
    """``max_{k,c,ω} |K̂_k(ω)|`` of ``(K, C, PH, PW//2 + 1)`` spectra: an upper bound of ``‖A‖`` for
    one kernel (not ``‖A‖``: the crop lowers it; use :func:`operator_norm`)."""
    return float(spectra.abs().amax())


def _settled(changes: list[float], tol: float) -> bool:
    """Whether the power iteration is within ``tol`` of its limit (module docstring).

    The rate ``ρ`` is taken over the last three changes since the first ones decay faster; a
    second singular value close to the first can hide early, hence ``MIN_ITERATIONS``.
    """
    if len(changes) < MIN_ITERATIONS:
        return False
    last = changes[-4:]
    rho = max(b / a if a > 0 else 0.0 for a, b in itertools.pairwise(last))
    return rho < 1 and changes[-1] * rho / (1 - rho) < tol and changes[-1] < tol


def operator_norm(op: OperatorLike, shape: tuple[int, ...] | None = None,
                  dtype: torch.dtype | None = None, tol: float = NORM_TOLERANCE,
                  max_iterations: int = NORM_MAX_ITERATIONS, seed: int = 0) -> float:
    """``‖A‖`` of ``op`` by power iteration on ``AᵀA`` (crop included), cached on ``op``.

    Parameters
    ----------
    op : object with ``A`` and ``A_adjoint``
    shape : tuple of int, optional
        Scene shape ``(B, C, H, W)``; default ``op.domain_shape()``.
    dtype : torch.dtype, optional
        Default ``op.dtype``.
    tol, max_iterations, seed
        As :func:`largest_eigenvalue`.

    Returns
    -------
    float
        The estimate of ``‖A‖`` (within about ``tol``, from below).
    """
    shape = tuple(shape) if shape is not None else op.domain_shape()
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
