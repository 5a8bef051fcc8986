r"""Physical constraints on kernels fitted from pairs, and the solver that enforces them.

A measured PSF is non-negative, lives on the caustic's footprint and carries a fixed energy.
:func:`projected_fit` minimises the same regularised least-squares objective as the
conjugate-gradient fit of :mod:`psfkit.pairs_fit`,

.. math::

    f(K) = \tfrac12\sum_i\lVert A_K x_i - y_i\rVert^2 + \tfrac\lambda2\lVert K\rVert^2
           + \tfrac\mu2\sum_{k\ge1}\lVert K_k - K_0\rVert^2 ,

over the closed convex set :math:`\mathcal C = \{K \ge 0,\ K = 0 \text{ outside the support},\
\textstyle\sum_{u} K_{k,c}(u) = e_{k,c}\}` (each part optional), by accelerated projected
gradient (FISTA) with the step ``1/L`` from a power-iteration estimate of the largest eigenvalue
of the normal operator and gradient-based adaptive restart (O'Donoghue & Candès 2015). The
energy constraint is enforced by the exact Euclidean projection onto the scaled simplex
(:func:`project`), so every iterate is feasible and the energies hold to rounding, rather than
by a rescale after clipping (which is not a projection and would break the convergence of FISTA).
Colour channels are independent problems: each gets its own step size and restarts.

FISTA converges slowly when the normal operator is ill-conditioned (the pairs' Gram is).
For the non-negativity constraint alone, :func:`psfkit.pairs_solver.projected_newton` solves
the same problem to a KKT residual orders of magnitude smaller for the same work.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.errors import InvalidInputError
from psfkit.forward.norm import largest_eigenvalue

Normal = Callable[[Tensor], Tensor]


def project(kernels: Tensor, nonneg: bool = True, support: Tensor | None = None,
            energy: Tensor | None = None) -> Tensor:
    """Euclidean projection of ``(K, C, Hk, Wk)`` kernels onto the constraint set.

    Parameters
    ----------
    kernels : Tensor
        ``(K, C, Hk, Wk)``.
    nonneg : bool
        ``K >= 0``.
    support : Tensor, optional
        ``(Hk, Wk)`` boolean: pixels outside are set to zero.
    energy : Tensor, optional
        ``(K, C)`` sums (must be > 0 with ``nonneg``): with ``nonneg`` the projection onto the
        scaled simplex ``{K >= 0, Σ K = e}`` (sort-based, Held et al. 1974), without it onto
        the hyperplane ``Σ K = e`` (a constant shift of the supported pixels).

    Returns
    -------
    Tensor
        The projected kernels, same shape and dtype.
    """
    k, c, h, w = kernels.shape
    flat = kernels.reshape(k * c, h * w)
    mask = None if support is None else support.reshape(1, h * w).to(torch.bool)
    if energy is None:
        out = flat.clamp_min(0) if nonneg else flat.clone()
        if mask is not None:
            out = out * mask
        return out.reshape(k, c, h, w)
    # float64 for the cumulative sums: the energies then hold to ~1e-12, not float32's 1e-4
    v = flat.to(torch.float64)
    target = energy.reshape(k * c, 1).to(torch.float64)
    count = h * w if mask is None else int(mask.sum())
    if count == 0:
        raise InvalidInputError("the kernel support is empty: no pixel can carry the energy")
    if not nonneg:
        inside = v if mask is None else v * mask
        shift = (target - inside.sum(dim=1, keepdim=True)) / count
        out = v + shift if mask is None else (v + shift) * mask
        return out.to(kernels.dtype).reshape(k, c, h, w)
    if bool((target <= 0).any()):
        raise InvalidInputError("a non-negative kernel needs a positive energy; got "
                                f"{target.min().item():.3g}")
    # outside the support: -inf sorts last and is never among the first `count` entries
    masked = v if mask is None else v.masked_fill(~mask, -torch.inf)
    u = torch.sort(masked, dim=1, descending=True).values[:, :count]
    cssv = u.cumsum(dim=1) - target
    index = torch.arange(1, count + 1, dtype=v.dtype, device=v.device)
    active = (u - cssv / index) > 0
    rho = (active * index).argmax(dim=1, keepdim=True)       # last active position (0-based)
    theta = cssv.gather(1, rho) / (rho + 1).to(v.dtype)
    out = (v - theta).clamp_min(0)
    if mask is not None:
        out = out * mask
    return out.to(kernels.dtype).reshape(k, c, h, w)


def auto_support(base: np.ndarray, threshold: float = 0.1, smoothing: float = 1.0,
                 dilation: int = 2) -> np.ndarray:
    """The caustic footprint of a fitted (unconstrained) PSF ``(C, Hk, Wk)``.

    ``|K|`` is averaged over channels, smoothed with a Gaussian of ``smoothing`` pixels (the
    negative lobes of an unconstrained fit sit next to the caustic lines: their magnitude marks
    the footprint too), thresholded at ``threshold`` × its maximum, and dilated by ``dilation``
    pixels so that the edge of the caustic is not cut.

    Returns
    -------
    numpy.ndarray
        ``(Hk, Wk)`` bool.
    """
    from scipy.ndimage import binary_dilation, gaussian_filter

    magnitude = np.abs(np.asarray(base, dtype=np.float64)).mean(axis=0)
    smooth = gaussian_filter(magnitude, smoothing) if smoothing > 0 else magnitude
    mask = smooth >= threshold * smooth.max() if smooth.max() > 0 else np.ones_like(smooth,
                                                                                     bool)
    if dilation > 0:
        mask = binary_dilation(mask, iterations=dilation)
    return mask


def _per_channel_norm(a: Tensor) -> Tensor:
    return a.pow(2).sum(dim=(0, 2, 3)).sqrt()                                  # (C,)


#: Relative accuracy of the step-size eigenvalue (a step size needs no more).
LIPSCHITZ_TOLERANCE = 1e-2


def lipschitz(normal: Normal, like: Tensor, seed: int = 0) -> Tensor:
    """Largest eigenvalue of the (per-channel block-diagonal, positive semi-definite) normal
    operator, per channel ``(C,)``, times 1.05: :func:`psfkit.forward.norm.largest_eigenvalue`
    (the one estimator; to ``LIPSCHITZ_TOLERANCE``) approaches it from below, and a step of
    ``1/L`` needs ``L`` at least the eigenvalue."""
    value = largest_eigenvalue(normal, tuple(like.shape), like.dtype, like.device, block_dim=1,
                               tol=LIPSCHITZ_TOLERANCE, seed=seed)
    return 1.05 * value.to(dtype=like.dtype, device=like.device)


def projected_fit(normal: Normal, rhs: Tensor, start: Tensor, iterations: int,
                  nonneg: bool = True, support: Tensor | None = None,
                  energy: Tensor | None = None, tolerance: float = 1e-6,
                  bar: Any = None) -> tuple[Tensor, dict[str, Any]]:
    """FISTA with adaptive restart for ``min ½KᵀNK − rhsᵀK`` over the constraint set.

    Parameters
    ----------
    normal : callable
        ``K ↦ N K`` (the regularised normal operator, block-diagonal over channels).
    rhs : Tensor
        ``(K, C, Hk, Wk)``, ``Bᵀy``.
    start : Tensor
        Warm start (projected first), e.g. the unconstrained solution.
    iterations : int
        Gradient steps (one application of ``normal`` each, plus those of the step size's power
        iteration, :func:`lipschitz`).
    nonneg, support, energy
        The constraints (:func:`project`).
    tolerance : float
        Stop when every channel's relative change ``‖K⁺ − K‖/‖K‖`` falls below this.

    Returns
    -------
    (Tensor, dict)
        The kernels (feasible) and ``{"iterations", "restarts", "relative_change",
        "lipschitz"}``.
    """
    step = 1.0 / lipschitz(normal, start)[None, :, None, None]
    x = project(start, nonneg, support, energy)
    z = x.clone()
    t = torch.ones(start.shape[1], dtype=start.dtype, device=start.device)
    restarts, done, change = 0, 0, float("nan")
    while done < iterations:
        done += 1
        x_new = project(z - step * (normal(z) - rhs), nonneg, support, energy)
        delta = x_new - x
        change = float((_per_channel_norm(delta)
                        / _per_channel_norm(x_new).clamp_min(1e-30)).max())
        # restart a channel whose momentum points uphill: (z − x⁺)·(x⁺ − x) > 0
        uphill = ((z - x_new) * delta).sum(dim=(0, 2, 3)) > 0
        restarts += int(uphill.sum())
        t_new = (1 + torch.sqrt(1 + 4 * t * t)) / 2
        momentum = torch.where(uphill, torch.zeros_like(t), (t - 1) / t_new)
        t = torch.where(uphill, torch.ones_like(t), t_new)
        z = x_new + momentum[None, :, None, None] * delta
        x = x_new
        if bar is not None:
            bar.update(1)
        if change < tolerance:
            break
    return x, {"method": "fista", "iterations": done, "restarts": restarts,
               "relative_change": change,
               "lipschitz": [float(v) for v in (1.0 / step).flatten()]}


def kernel_summary(kernels: np.ndarray) -> dict[str, Any]:
    """What the kernel file records about a fitted model's physics: per-kernel, per-channel
    energies (sums) ``[K][C]``, the support fraction (pixels non-zero in some kernel or
    channel), and the count of negative and non-finite pixels."""
    k = np.asarray(kernels, dtype=np.float64)
    return {"energy": [[float(e) for e in row] for row in k.sum(axis=(-2, -1))],
            "support_fraction": float(np.any(k != 0, axis=(0, 1)).mean()),
            "negative_pixels": int((k < 0).sum()),
            "nonfinite_pixels": int((~np.isfinite(k)).sum())}
