r"""ADMM-TV with closed-form steps for sensor-side eigen-kernel models (and the SI model).

The DiffuserCam ADMM (:mod:`ekdun.models.tv_admm_steps`) splits ``v = Hx`` so that every step
is diagonal in Fourier space or per pixel. The sensor-side eigen-kernel model
``A x = Σ_k W_k ⊙ C H_k x`` (``H_k`` the circular convolution with kernel ``k`` on the padded
grid, ``C`` the crop, ``W_k`` the weight maps) keeps that property with one split per kernel,
``u_k = H_k x``:

.. math::

    \min_{x \ge 0}\ \tfrac12 \Big\lVert y - \sum_k W_k \odot C u_k \Big\rVert^2
        + \lambda\lVert s\rVert_1
    \quad\text{s.t.}\quad u_k = H_k x,\ s = \Psi x,\ w = x .

* ``u`` step: outside the sensor ``u_k = b_k = H_k x + α_k/μ_1``; inside it each pixel solves
  ``(w wᵀ + μ_1 I) u = w y + μ_1 b`` (``w`` the ``K`` weights of the pixel), by
  Sherman–Morrison ``u = b + w (y − wᵀb)/(μ_1 + wᵀw)``;
* ``x`` step: ``(μ_1 Σ_k H_kᵀH_k + μ_2 ΨᵀΨ + μ_3) x = …`` is diagonal in Fourier space;
* ``s``, ``w``: soft threshold and ``max(·, 0)`` as in the SI ADMM.

One iteration costs ``2K + 2`` FFTs (SI: 4, exactly the steps of
:func:`~ekdun.models.tv_admm_steps.admm_tv_iteration`). The scene lives on the padded grid
(light from outside the view, as in :mod:`ekdun.reconstruction.extended_scene`) and the
central block is returned. Units are those of :mod:`ekdun.reconstruction.pdhg_tv`: the
measurement is divided by its peak and the operator by ``‖A‖``
(:func:`psfkit.forward.norm.operator_norm`, the one estimate, cached on the operator), so
``tv`` and the ``μ`` are scale-free and the objective is PDHG's at the same ``tv`` (tested).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, TensorShapeError
from ekdun.models.tv_admm_steps import (
    finite_difference_spectrum,
    finite_differences,
    finite_differences_adjoint,
)
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from ekdun.reconstruction.pdhg_tv import TVResult
from psfkit.forward.convolution import kernel_images, padded_scene_adjoint_spectrum
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.norm import operator_norm


@dataclass
class NormalisedProblem:
    """A measurement and a model in the scale-free units of the ADMM solvers: ``y`` divided by
    its ``peak``, the kernel spectra (and their conjugates) by the gain ``norm``."""

    y: Tensor
    peak: float
    norm: float
    spectra: Tensor
    conj: Tensor


def normalised_problem(measurement: Tensor, op: ExtendedSceneOperator, tv: float, tol: float,
                       iterations: int, penalties: tuple[float, ...],
                       norm: float | None) -> NormalisedProblem:
    """Check the arguments common to the ADMM solvers and scale the problem (see the module
    docstring); raises :class:`~ekdun.errors.ConfigurationError` or
    :class:`~ekdun.errors.TensorShapeError`."""
    if tv < 0 or tol < 0 or iterations < 1 or min(penalties) <= 0:
        raise ConfigurationError("need tv >= 0, tol >= 0, iterations >= 1 and positive mu")
    if measurement.ndim != 3:
        raise TensorShapeError(f"measurement must be (C, H, W), got {tuple(measurement.shape)}")
    op.check(measurement[None], "measurement")
    norm = operator_norm(op) if norm is None else norm
    peak = float(measurement.abs().max().clamp_min(1e-30))
    return NormalisedProblem(measurement / peak, peak, norm, op.base.spectra / norm,
                             op.base.conj_spectra / norm)


def record_change(result: TVResult, iteration: int, x_new: Tensor, x: Tensor, tol: float,
                  callback: Callable[[int, float], None] | None) -> bool:
    """Log ``‖x_new − x‖/‖x_new‖`` in ``result`` (and to ``callback``); whether the stopping
    rule ``change < tol`` holds (``result.converged`` is set then). An iterate of zero counts as
    no convergence (the source-side ADMM's first ``x`` is 0)."""
    size = float(x_new.norm())
    change = float((x_new - x).norm()) / size if size > 0 else 1.0
    result.relative_change.append(change)
    if callback is not None:
        callback(iteration, change)
    result.converged = tol > 0 and change < tol
    return result.converged


def ek_admm_tv(measurement: Tensor, op: ExtendedSceneOperator, tv: float = 1e-3,
               iterations: int = 100, nonneg: bool = True, tol: float = 0.0,
               mu1: float = 0.05, mu2: float = 0.01, mu3: float = 0.003,
               norm: float | None = None,
               callback: Callable[[int, float], None] | None = None) -> TVResult:
    """ADMM-TV for a sensor-side (or shift-invariant) model with the scene on the padded grid.

    Parameters
    ----------
    measurement : Tensor
        ``(C, H', W')`` in the operator's dtype.
    op : ExtendedSceneOperator
        The model (its spectra ``(K, C, PH, PW//2+1)`` and weights ``(K, H', W')`` or none).
    tv : float
        Relative TV weight (as :func:`~ekdun.reconstruction.pdhg_tv.pdhg_tv`'s).
    iterations : int
        Maximum iterations.
    nonneg : bool
        Keep the ``w = x ≥ 0`` split (else no image constraint).
    tol : float
        Stop once ``‖x_k − x_{k−1}‖/‖x_k‖ < tol`` (0: off).
    mu1, mu2, mu3 : float
        Penalties of the ``u``, ``s`` and ``w`` splits in the normalised units (they change
        the speed, not the minimiser; the defaults were the fastest at 100 iterations on two
        DLMD pairs at 67x120, among 0.003-0.3 for ``μ1``, ``μ3`` and 0.003-0.03 for ``μ2``).
    norm : float, optional
        ``‖A‖``, which sets the units (default :func:`psfkit.forward.norm.operator_norm`; any
        positive value gives the same minimiser for the correspondingly scaled ``tv``).
    callback : callable, optional
        ``callback(iteration, relative_change)``.

    Returns
    -------
    TVResult
        ``image`` is the ``(C, PH, PW)`` padded-grid scene in the units of ``y = A x``
        (``op.crop`` gives the sensor-sized block).
    """
    if op.convention != "sensor":
        raise ConfigurationError("ek_admm_tv needs a sensor-side or shift-invariant model "
                                 "(source-side models: source_admm_tv)")
    problem = normalised_problem(measurement, op, tv, tol, iterations, (mu1, mu2, mu3), norm)
    y, spectra, conj = problem.y, problem.spectra, problem.conj   # (K, C, PH, PW//2+1)
    grid, sensor = op.grid_shape, op.sensor_shape
    n_kernels = int(spectra.shape[0])
    weights = (torch.ones((n_kernels, *sensor), dtype=y.dtype, device=y.device)
               if op.weights is None else op.weights)[:, None]    # (K, 1, H', W')
    gain = 1.0 / (mu1 + (weights ** 2).sum(dim=0))                # (1, H', W')
    m3 = mu3 if nonneg else 0.0
    power = (spectra.abs() ** 2).sum(dim=0)                       # Σ_k |K̂_k|²
    inverse = 1.0 / (mu1 * power + mu2 * finite_difference_spectrum(grid, y.dtype) + m3)
    # x̂⁺ = inverse·F(rhs) + keep·x̂ + lift·F(Aᵀr) (see the loop).
    keep = mu1 * power * inverse
    lift = mu1 * inverse                                          # (C, PH, PW//2+1)
    shift_invariant = op.weights is None
    x = torch.zeros((op.channels, *grid), dtype=y.dtype, device=y.device)
    x_hat = rfft2(x)
    dx = finite_differences(x)
    # Only the in-view blocks of H_k x and of the u-duals are ever read.
    hx = torch.zeros((n_kernels, op.channels, *sensor), dtype=y.dtype, device=y.device)
    alpha1, alpha3 = torch.zeros_like(hx), torch.zeros_like(x)
    alpha2 = torch.zeros((2, *x.shape), dtype=y.dtype, device=y.device)
    track = tol > 0 or callback is not None
    result = TVResult(image=x, iterations=0, converged=False, operator_norm=problem.norm)
    for k in range(1, iterations + 1):
        s = torch.nn.functional.softshrink(dx + alpha2 / mu2, tv / mu2)
        # u_k = b_k + pad(W_k r), b_k = H_k x + α_k/μ1 (Sherman–Morrison inside the view).
        b = hx + alpha1 / mu1
        if shift_invariant:
            residual = (y - b[0]) * gain                                   # (C, H', W')
            correction = residual[None]                                    # (1, C, H', W')
        else:
            residual = (y - (weights * b).sum(dim=0)) * gain               # (C, H', W')
            correction = weights * residual                                # (K, C, H', W')
        rhs = finite_differences_adjoint(mu2 * s - alpha2)
        if nonneg:
            w = torch.relu(x + alpha3 / mu3)
            rhs += mu3 * w - alpha3
        # μ1 u_k − α_k = μ1 (H_k x + pad(W_k r)) everywhere: the duals cancel, and
        # F(H_k x) = K̂_k x̂, so the data part of the right-hand side is F(Aᵀr): K FFTs of
        # the in-view corrections only (Eq. 7's adjoint, psfkit.forward).
        x_hat = rfft2(rhs).mul_(inverse).addcmul_(keep, x_hat)
        x_hat += lift * padded_scene_adjoint_spectrum(residual, conj, op.weights, grid)
        x_new = irfft2(x_hat, grid)
        hx_new = kernel_images(x_hat, spectra, grid, sensor)     # crop(H_k x⁺), (K, C, H', W')
        alpha1 = mu1 * (hx_new - hx - correction)      # α_k + μ1 (H_k x⁺ − u_k), in view
        hx = hx_new
        dx = finite_differences(x_new)                 # also the next iteration's Ψx
        alpha2 = alpha2 + mu2 * (dx - s)
        if nonneg:
            alpha3 = alpha3 + mu3 * (x_new - w)
        result.iterations = k
        stop = track and record_change(result, k, x_new, x, tol, callback)
        x = x_new
        if stop:
            break
    image = x.clamp_min(0) if nonneg else x
    result.image = image * (problem.peak / problem.norm)
    return result
