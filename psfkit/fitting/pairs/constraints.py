"""Physical constraints on kernels fitted from pairs, and the one solver that imposes them.

A measured PSF is non-negative and lives on the caustic's footprint. :func:`projected_newton`
(projected Newton-CG, Bertsekas 1982: the Newton step on the free pixels by a few
preconditioned CG iterations, then an Armijo search along the projection arc) minimises the CG
fit's objective (:mod:`psfkit.fitting.pairs.solver`) over ``K ≥ 0`` (and ``K = 0`` outside a
support) to a relative KKT residual ``‖K − max(0, K − ∇/L)‖ / ‖K‖`` per channel;
:func:`newton_fit` runs it on a fit's normal equations. A support alone is a linear constraint,
solved exactly by :func:`support_least_squares`. :func:`auto_support` gives the footprint,
:func:`kernel_summary` what the kernel file records.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.fitting.pairs.solver import (
    _per_channel_dot,
    regularised_normal,
    solve_normal_equations,
)
from psfkit.forward.norm import largest_eigenvalue

Normal = Callable[[Tensor], Tensor]

#: Steps without a new lowest KKT residual after which :func:`projected_newton` checks whether
#: its cheap Hessian products are what holds it back (:func:`_cheap_products_too_coarse`): then
#: it goes on with the exact ones; else with twice the CG iterations per Newton step, up to
#: ``MAX_CG_GROWTH`` times the given ones (DLMD at full resolution: 20 per step swung between
#: 2e-6 and 1e-4 for 100 steps; 40 converged in 73).
STALL_STEPS = 20
MAX_CG_GROWTH = 4


def auto_support(base: np.ndarray, threshold: float = 0.1, smoothing: float = 1.0,
                 dilation: int = 2) -> np.ndarray:
    """The caustic footprint ``(Hk, Wk)`` bool of a fitted (unconstrained) PSF ``(C, Hk, Wk)``.

    ``|K|`` averaged over channels (negative lobes mark the footprint too), smoothed by a Gaussian
    of ``smoothing`` px, thresholded at ``threshold`` × its maximum and dilated by ``dilation`` px.
    """
    from scipy.ndimage import binary_dilation, gaussian_filter

    magnitude = np.abs(np.asarray(base, dtype=np.float64)).mean(axis=0)
    smooth = gaussian_filter(magnitude, smoothing) if smoothing > 0 else magnitude
    mask = smooth >= threshold * smooth.max() if smooth.max() > 0 else np.ones_like(smooth,
                                                                                     bool)
    if dilation > 0:
        mask = binary_dilation(mask, iterations=dilation)
    return mask


#: Relative accuracy of the step-size eigenvalue (a step size needs no more).
LIPSCHITZ_TOLERANCE = 1e-2


def lipschitz_constant(normal: Normal, like: Tensor, seed: int = 0) -> Tensor:
    """1.05 × the largest eigenvalue per channel ``(C,)`` of the block-diagonal normal operator
    (the estimate approaches it from below; a ``1/L`` step needs ``L`` above it)."""
    value = largest_eigenvalue(normal, tuple(like.shape), like.dtype, like.device, block_dim=1,
                               tol=LIPSCHITZ_TOLERANCE, seed=seed)
    return 1.05 * value.to(dtype=like.dtype, device=like.device)


def kernel_summary(kernels: np.ndarray) -> dict[str, Any]:
    """What the kernel file records about a fitted model's physics: energies ``[K][C]``, support
    fraction, counts of negative and non-finite pixels."""
    k = np.asarray(kernels, dtype=np.float64)
    return {"energy": [[float(e) for e in row] for row in k.sum(axis=(-2, -1))],
            "support_fraction": float(np.any(k != 0, axis=(0, 1)).mean()),
            "negative_pixels": int((k < 0).sum()),
            "nonfinite_pixels": int((~np.isfinite(k)).sum())}


def _per_channel_norm(a: Tensor) -> Tensor:
    return a.pow(2).sum(dim=(0, 2, 3)).sqrt()                                  # (C,)


def _natural_residual(kernels: Tensor, gradient: Tensor, lipschitz: Tensor,
                      support: Tensor | None = None) -> Tensor:
    r"""Per-channel relative natural residual ``(C,)`` of ``min ½KᵀNK − rhsᵀK`` over ``K ≥ 0`` (and
    ``K = 0`` outside ``support``), from the ``gradient`` ``NK − rhs``:

    .. math:: \lVert K - \max(0, K - \nabla/L)\rVert \,/\, \lVert K\rVert ,

    0 exactly at the minimiser and independent of units.
    """
    step = kernels - (kernels - gradient / lipschitz[None, :, None, None]).clamp_min(0)
    if support is not None:                  # pixels held at 0 have no optimality condition
        step = step * support
    return _per_channel_norm(step) / _per_channel_norm(kernels).clamp_min(1e-300)


def _cheap_products_too_coarse(normal: Normal, cheap: Normal, step: Tensor,
                               forcing: float) -> bool:
    """Whether the cheap products miss the last Newton step ``d`` by more than its CG's forcing,
    ``‖(Ñ − N) d‖ > forcing · ‖N d‖`` in some channel (or gave no step); otherwise a stall is the
    active set's swing and exact products would only double the cost."""
    exact = normal(step)
    size = _per_channel_norm(exact)
    error = _per_channel_norm(cheap(step) - exact)
    return bool(((error > forcing * size) | (size == 0)).any())


def _armijo_step(normal: Normal, cheap: Normal, project: Normal, x: Tensor, nx: Tensor,
                 g: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``x⁺ = project(x + αd)`` with the largest ``α = 2⁻ʲ`` (``j < 30``) decreasing the objective
    by at least ``10⁻⁴ gᵀ(x⁺ − x)``, per channel, and ``N x⁺``; channels where none does keep ``x``
    (``accepted`` false). Backtracking trials use ``cheap``; one exact product checks the result."""
    alpha = torch.ones(g.shape[1], dtype=x.dtype, device=x.device)
    accepted = torch.zeros_like(alpha, dtype=torch.bool)
    x_new, nx_new = x, nx
    backtracked = False
    for trial_index in range(30):
        trial = project(x + alpha[None, :, None, None] * d)
        change = trial - x
        exact = trial_index == 0 or cheap is normal
        n_trial = normal(trial) if exact else None
        n_change = cheap(change) if n_trial is None else n_trial - nx
        # the decrease f(x + s) − f(x) = sᵀ(g + ½Ns) taken directly: the difference of
        # two objective values loses it to rounding near the minimiser
        decrease = _per_channel_dot(change, g + 0.5 * n_change)
        ok = decrease <= 1e-4 * _per_channel_dot(g, change)
        take = ok & ~accepted
        x_new = torch.where(take[None, :, None, None], trial, x_new)
        if n_trial is not None:
            nx_new = torch.where(take[None, :, None, None], n_trial, nx_new)
        backtracked |= not exact and bool(take.any())
        accepted |= ok
        if bool(accepted.all()):
            break
        alpha = torch.where(accepted, alpha, alpha / 2)
    if backtracked:
        # the exact product checks the cheap trials' verdict: a channel whose decrease does
        # not hold exactly keeps x and counts as not descending (the caller then goes on
        # with exact products)
        nx_new = normal(x_new)
        change = x_new - x
        holds = (_per_channel_dot(change, g + 0.5 * (nx_new - nx))
                 <= 1e-4 * _per_channel_dot(g, change))
        keep = (accepted & ~holds)[None, :, None, None]
        x_new, nx_new = torch.where(keep, x, x_new), torch.where(keep, nx, nx_new)
        accepted &= holds
    return x_new, nx_new, accepted


def projected_newton(normal: Callable[[Tensor], Tensor], rhs: Tensor, start: Tensor,
                     precondition: Callable[[Tensor], Tensor] | None = None,
                     iterations: int = 50, cg_iterations: int = 20, tolerance: float = 1e-10,
                     bar: Any = None, support: Tensor | None = None,
                     hessian: Callable[[Tensor], Tensor] | None = None
                     ) -> tuple[Tensor, dict[str, Any]]:
    """Projected Newton-CG for ``min ½KᵀNK − rhsᵀK`` over ``K ≥ 0``, per channel.

    Each step: ``g = NK − rhs``; the binding pixels ``{K = 0, g > 0}`` stay at 0; on the others
    CG for the Newton step ``N_F d = −g_F``; then ``K⁺ = max(0, K + αd)`` with an Armijo ``α``. The
    Newton CG and the backtracking trials may use a cheaper ``hessian``; accepted decreases,
    gradients and the stopping test are exact.

    Parameters
    ----------
    normal : callable
        ``K ↦ N K``, symmetric positive semi-definite per channel.
    rhs : Tensor
        ``(K, C, Hk, Wk)``.
    start : Tensor
        Warm start (clipped to ``≥ 0``).
    precondition : callable, optional
        Symmetric positive definite approximation of ``N⁻¹``, applied as ``P_F M P_F``.
    iterations, cg_iterations
        Most Newton steps, and CG iterations per step.
    tolerance : float
        Stop when every channel's relative KKT residual is below this.
    support : Tensor, optional
        Boolean, broadcastable to the kernels: pixels outside it are held at 0.
    hessian : callable, optional
        Approximation of ``normal``; after ``STALL_STEPS`` steps without a new low the steps go
        on with ``normal`` if it is too coarse, else with twice the CG iterations.

    Returns
    -------
    (Tensor, dict)
        The kernels (``≥ 0``) and ``{"method", "iterations", "kkt_residual", "history",
        "converged", "stalled", ...}``; ``stalled``: some channel found no descending step.
    """
    inside = None if support is None else support.to(start.dtype)
    cheap = normal if hessian is None else hessian
    exact_from = 0 if hessian is None else None

    def project(v: Tensor) -> Tensor:
        v = v.clamp_min(0)
        return v if inside is None else v * inside

    x = project(start)
    lipschitz = lipschitz_constant(cheap, x)
    history: list[float] = []
    done = 0
    stuck = torch.zeros(rhs.shape[1], dtype=torch.bool, device=rhs.device)
    best = torch.full((rhs.shape[1],), float("inf"), dtype=rhs.dtype, device=rhs.device)
    since = torch.zeros(rhs.shape[1], dtype=torch.int64, device=rhs.device)
    nx = normal(x)
    last: tuple[Tensor, float] | None = None           # the last Newton step and its forcing
    cg_cap = cg_iterations
    while True:
        g = nx - rhs
        residual = _natural_residual(x, g, lipschitz, inside)
        history.append(float(residual.max()))
        improved = residual < best
        best = torch.where(improved, residual, best)
        since = torch.where(improved, torch.zeros_like(since), since + 1)
        cheap_stuck = cheap is not normal and bool(stuck.any())
        if cheap_stuck or (last is not None and bool((since >= STALL_STEPS).any())):
            if cheap is not normal and (cheap_stuck or _cheap_products_too_coarse(
                    normal, cheap, *last)):
                # the cheap products are too coarse for this problem's conditioning: go on
                # with the exact ones
                cheap, exact_from = normal, done
                stuck[:] = False
            else:
                # the steps are too inexact for the active set to settle: solve them further
                cg_cap = min(2 * cg_cap, MAX_CG_GROWTH * cg_iterations)
                since.zero_()
        if bool(((residual < tolerance) | stuck).all()) or done >= iterations:
            break
        done += 1
        bound = (x == 0) & (g > 0)
        free = (~bound).to(x.dtype)
        if inside is not None:
            free = free * inside

        def masked(v: Tensor, free: Tensor = free, product: Any = cheap) -> Tensor:
            return product(v * free) * free

        def masked_precondition(r: Tensor, free: Tensor = free) -> Tensor:
            return (r * free if precondition is None else precondition(r * free) * free)

        # inexact Newton: the CG solves the step only as accurately as the KKT residual
        # calls for (forcing term √residual, Eisenstat & Walker 1996): far from the solution
        # the active set still changes and a precise step is wasted
        forcing = min(0.1, float(residual.max()) ** 0.5)
        d, _ = solve_normal_equations(masked, -g * free, masked_precondition,
                                      tolerance=forcing, max_iterations=cg_cap,
                                      true_residual=False)
        last = (d, forcing)
        x, nx, accepted = _armijo_step(normal, cheap, project, x, nx, g, d)
        stuck |= ~accepted
        if bar is not None:
            bar.update(1)
    return x, {"method": "projected-newton-cg", "iterations": done,
               "kkt_residual": history[-1], "history": history,
               "converged": history[-1] < tolerance, "stalled": bool(stuck.any()),
               "exact_hessian_from": exact_from, "cg_iterations_last": cg_cap}


def newton_fit(system: dict[str, Any], start: Tensor, mask: Tensor | None, steps: int,
               cg_iterations: int, tolerance: float, progress: bool = False
               ) -> tuple[Tensor, dict[str, Any]]:
    """Non-negative kernels (zero outside ``mask``) on the normal equations ``system`` of
    :func:`~psfkit.fitting.pairs.solver.solve_kernels`, by :func:`projected_newton` from
    ``start``, its CG and backtracking on float32 products (``system["twin"]``).

    Preconditioned kernel by kernel (``coupled=False``): the free set differs between kernels, and
    the coupled blocks restricted to it stopped converging on DLMD. Returns the kernels and the
    record (``kkt_history``).
    """
    from tqdm.auto import tqdm

    batches = system["batches"]
    twin = system.get("twin")
    if twin is None and batches.dtype == torch.float64:
        twin = batches.astype(torch.float32)
    hessian = None if twin is None else regularised_normal(twin, system["lambda"],
                                                           system["mu"])
    # in the float32 products' precision, not the working one (a preconditioner needs no more)
    precondition = system["gram"].preconditioner(system["lambda"], system["mu"], coupled=False,
                                                 dtype=None if twin is None else twin.dtype)
    with tqdm(total=steps, unit="it", leave=False, desc="projected Newton",
              disable=not progress) as bar:
        kernels, info = projected_newton(system["normal"], system["rhs"], start,
                                         precondition, steps, cg_iterations, tolerance,
                                         bar=bar, support=mask, hessian=hessian)
    info = {k: v for k, v in info.items() if k != "history"} | {
        "kkt_history": info["history"], "cg_iterations": cg_iterations,
        "float32_passes": 0 if twin is None else twin.passes}
    return kernels, info


def support_least_squares(system: dict[str, Any], start: Tensor, mask: Tensor,
                          tolerance: float, max_iterations: int
                          ) -> tuple[Tensor, dict[str, Any]]:
    """Least squares with the kernels zero outside ``mask``: preconditioned CG restricted to the
    support (``S N S``, ``S P S``), from ``start`` cut to it."""
    inside = mask.to(start.dtype)
    normal, precondition = system["normal"], system["precondition"]
    kernels, info = solve_normal_equations(
        lambda v: normal(v * inside) * inside, system["rhs"] * inside,
        lambda r: precondition(r * inside) * inside, start * inside, tolerance,
        max_iterations)
    return kernels, {**info.as_dict(), "restricted_to_support": True}
