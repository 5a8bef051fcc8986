r"""ADMM-TV for every kernel model: one solver, one update rule per form of the model.

For a measurement ``y`` ``(C, H', W')`` and a model ``A`` whose scene ``x`` lives on the padded
grid ``(C, PH, PW)`` (:class:`~ekdun.reconstruction.extended_scene.ExtendedSceneOperator`):

.. math::

    \min_{x}\ \tfrac12 \lVert A x - y\rVert_2^2 + \lambda \lVert \Psi x\rVert_1
              \;[+\ \iota_{x \ge 0}(x)]

with ``Ψ`` circular forward differences. :func:`solve_tv` divides ``y`` by its peak and ``A``
by ``‖A‖`` (:func:`psfkit.forward.norm.operator_norm`), so ``tv`` and the penalties ``μ`` are
scale-free (``λ = tv · peak(|y|) · ‖A‖``) and scales the result back; it splits ``s = Ψx``
(soft threshold) and a copy of ``x`` (non-negativity) and stops when
``‖x_k − x_{k−1}‖/‖x_k‖ < tol``. The data term's split differs per rule (scaled duals):

:class:`ShiftInvariantRule`, ``A x = C H x``
    the DiffuserCam ADMM (Antipa et al. 2018; cf. :mod:`ekdun.nets.tv_admm_steps`), split
    ``u = Hx``: in the view ``u = b + (y − b)/(1 + μ1)``, ``b = Hx + α/μ1``, outside ``u = b``;
    the ``x`` step ``(μ1 HᵀH + μ2 ΨᵀΨ + μ3) x = …`` is diagonal in Fourier space.
:class:`SensorSideRule`, ``A x = Σ_k W_k ⊙ C H_k x``
    ``u_k = H_k x``; in the view each pixel solves ``(w wᵀ + μ1 I) u = w y + μ1 b`` by
    Sherman–Morrison, ``u = b + w (y − wᵀb)/(μ1 + wᵀw)``; since
    ``μ1 u_k − α_k = μ1 (H_k x + pad(W_k r))`` the ``x`` step's data part is ``F(Aᵀr)``.
:class:`SourceSideRule`, ``A x = C Σ_k H_k (V_k ⊙ x)``
    two-block ADMM over ``v = Σ_k H_k r_k, r_k = V_k z, s = Ψx, z = x`` (duals ``a, b_k, c, d``):

    * ``v = (Cᵀy + μ1 (Σ_k H_k r_k + a)) / (CᵀC + μ1)``, per pixel;
    * ``z = max(0, (μ4 Σ_k V_k (r_k + b_k) + μ3 (x − d)) / (μ4 Σ_k V_k² + μ3))``, per pixel;
    * ``s = 𝒮_{λ/μ2}(Ψx + c)``;
    * ``r``: per frequency ``(μ1 ĥĥᴴ + μ4 I) r̂ = μ1 ĥ̄ p̂ + μ4 t̂`` with ``ĥ = (K̂_k)_k``,
      ``p = v − a``, ``t_k = V_k z − b_k``; by Sherman–Morrison ``r̂_k = t̂_k + K̂_k^* ĝ``,
      ``ĝ = μ1 (p̂ − Σ_k K̂_k t̂_k) / (μ4 + μ1 Σ_k |K̂_k|²)``;
    * ``x = (μ2 ΨᵀΨ + μ3)⁻¹ (μ2 Ψᵀ(s − c) + μ3 (z + d))``, diagonal in Fourier space;
    * ``a += Σ_k H_k r_k − v``, ``b_k += r_k − V_k z``, ``c += Ψx − s``, ``d += z − x``.

    As ``b_k = H_kᵀ g`` after its update, only ``q = Σ_k V_k H_kᵀ g`` is kept.

The penalties change the speed, not the minimiser; the defaults are the fastest of a search
(research/notes/reconstruction-studies.md).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, TensorShapeError
from ekdun.nets.tv_admm_steps import (
    finite_difference_spectrum,
    finite_differences,
    finite_differences_adjoint,
)
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from psfkit.forward.convolution import crop, sum_of_kernel_products
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.norm import operator_norm
from psfkit.forward.padded_scene import kernel_images, padded_scene_adjoint_spectrum


@dataclass
class TVResult:
    """Result of :func:`solve_tv`: ``image`` ``(C, PH, PW)`` on the padded grid in the units
    of ``x`` in ``y = A x``, the iterations run, whether the ``tol`` rule stopped it, the
    relative change per iteration (with a ``tol`` or a callback) and the ``‖A‖`` used."""

    image: Tensor
    iterations: int
    converged: bool
    relative_change: list[float] = field(default_factory=list)
    operator_norm: float = 1.0


@dataclass
class NormalisedProblem:
    """``y`` divided by its ``peak`` and the kernel spectra (and conjugates) by ``norm``."""

    y: Tensor
    peak: float
    norm: float
    spectra: Tensor
    conj: Tensor


def normalised_problem(measurement: Tensor, op: ExtendedSceneOperator, tv: float, tol: float,
                       iterations: int, penalties: tuple[float, ...],
                       norm: float | None) -> NormalisedProblem:
    """Check the arguments and scale the problem (see the module docstring); raises
    :class:`~ekdun.errors.ConfigurationError` or :class:`~ekdun.errors.TensorShapeError`."""
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
    """Log ``‖x_new − x‖/‖x_new‖`` in ``result`` (and to ``callback``); whether
    ``change < tol`` (sets ``result.converged``). A zero iterate never converges."""
    size = float(x_new.norm())
    change = float((x_new - x).norm()) / size if size > 0 else 1.0
    result.relative_change.append(change)
    if callback is not None:
        callback(iteration, change)
    result.converged = tol > 0 and change < tol
    return result.converged


class ADMMRule:
    """One form's ADMM-TV update: its state and :meth:`step`; :attr:`penalties` holds its
    default ``μ``, in order."""

    penalties: ClassVar[dict[str, float]] = {}

    def __init__(self, problem: NormalisedProblem, op: ExtendedSceneOperator, tv: float,
                 nonneg: bool, mu: dict[str, float]) -> None:
        self.problem, self.op, self.tv, self.nonneg, self.mu = problem, op, tv, nonneg, mu
        self.grid, self.sensor = op.grid_shape, op.sensor_shape
        self.x = self.zeros(op.channels, *self.grid)

    def zeros(self, *shape: int) -> Tensor:
        y = self.problem.y
        return torch.zeros(shape, dtype=y.dtype, device=y.device)

    def step(self) -> Tensor:
        """One iteration: the new ``x`` (also stored in ``self.x``)."""
        raise NotImplementedError


class SensorSideRule(ADMMRule):
    """Sensor-side eigen-kernel models: ``u_k = H_k x`` per kernel (only in-view blocks
    stored)."""

    penalties: ClassVar[dict[str, float]] = {"mu1": 0.05, "mu2": 0.01, "mu3": 0.003}

    def __init__(self, problem: NormalisedProblem, op: ExtendedSceneOperator, tv: float,
                 nonneg: bool, mu: dict[str, float]) -> None:
        super().__init__(problem, op, tv, nonneg, mu)
        mu1, mu2, mu3 = mu["mu1"], mu["mu2"], mu["mu3"]
        spectra = problem.spectra                                    # (K, C, PH, PW//2+1)
        n_kernels = int(spectra.shape[0])
        self.weights = (torch.ones((n_kernels, *self.sensor), dtype=problem.y.dtype,
                                   device=problem.y.device)
                        if op.weights is None else op.weights)[:, None]   # (K, 1, H', W')
        self.gain = 1.0 / (mu1 + (self.weights ** 2).sum(dim=0))     # (1, H', W')
        power = (spectra.abs() ** 2).sum(dim=0)                      # Σ_k |K̂_k|²
        self.inverse = 1.0 / (mu1 * power + mu2 * finite_difference_spectrum(
            self.grid, problem.y.dtype) + (mu3 if nonneg else 0.0))
        # x̂⁺ = inverse·F(rhs) + keep·x̂ + lift·F(Aᵀr) (see step).
        self.keep = mu1 * power * self.inverse
        self.lift = mu1 * self.inverse                               # (C, PH, PW//2+1)
        self.x_hat = rfft2(self.x)
        self.dx = finite_differences(self.x)
        self.hx = self.zeros(n_kernels, op.channels, *self.sensor)
        self.alpha1, self.alpha3 = torch.zeros_like(self.hx), torch.zeros_like(self.x)
        self.alpha2 = self.zeros(2, *self.x.shape)

    def data_residual(self, b: Tensor) -> tuple[Tensor, Tensor]:
        """``r = (y − Σ_k W_k b_k)/(μ1 + Σ_k W_k²)`` ``(C, H', W')`` and the in-view
        correction ``u_k − b_k = W_k r``."""
        residual = (self.problem.y - (self.weights * b).sum(dim=0)) * self.gain
        return residual, self.weights * residual                     # (K, C, H', W')

    def step(self) -> Tensor:
        mu1, mu2, mu3 = self.mu["mu1"], self.mu["mu2"], self.mu["mu3"]
        x = self.x
        s = torch.nn.functional.softshrink(self.dx + self.alpha2 / mu2, self.tv / mu2)
        # u_k = b_k + pad(W_k r), b_k = H_k x + α_k/μ1 (Sherman–Morrison inside the view).
        residual, correction = self.data_residual(self.hx + self.alpha1 / mu1)
        rhs = finite_differences_adjoint(mu2 * s - self.alpha2)
        if self.nonneg:
            w = torch.relu(x + self.alpha3 / mu3)
            rhs += mu3 * w - self.alpha3
        # μ1 u_k − α_k = μ1 (H_k x + pad(W_k r)) everywhere: the duals cancel, and
        # F(H_k x) = K̂_k x̂, so the data part of the right-hand side is F(Aᵀr): K FFTs of
        # the in-view corrections only (Eq. 7's adjoint, psfkit.forward).
        self.x_hat = rfft2(rhs).mul_(self.inverse).addcmul_(self.keep, self.x_hat)
        self.x_hat += self.lift * padded_scene_adjoint_spectrum(
            residual, self.problem.conj, self.op.weights, self.grid)
        x_new = irfft2(self.x_hat, self.grid)
        hx_new = kernel_images(self.x_hat, self.problem.spectra, self.grid, self.sensor)
        self.alpha1 = mu1 * (hx_new - self.hx - correction)    # α_k + μ1 (H_k x⁺ − u_k)
        self.hx = hx_new
        self.dx = finite_differences(x_new)                    # also the next iteration's Ψx
        self.alpha2 = self.alpha2 + mu2 * (self.dx - s)
        if self.nonneg:
            self.alpha3 = self.alpha3 + mu3 * (x_new - w)
        self.x = x_new
        return x_new


class ShiftInvariantRule(SensorSideRule):
    """One kernel, no weights: the sensor-side rule with ``W = 1``, without the products."""

    def data_residual(self, b: Tensor) -> tuple[Tensor, Tensor]:
        residual = (self.problem.y - b[0]) * self.gain                # (C, H', W')
        return residual, residual[None]                                # (1, C, H', W')


def _scale_complex(real: Tensor, spectrum: Tensor, out: Tensor | None = None) -> Tensor:
    """``real * spectrum`` for a real factor, through the real view (no complex copy of
    ``real``, which a mixed real-complex product makes)."""
    target = None if out is None else torch.view_as_real(out)
    product = torch.mul(torch.view_as_real(spectrum), real[..., None], out=target)
    return torch.view_as_complex(product) if out is None else out


class SourceSideRule(ADMMRule):
    """Source-side eigen-kernel models: the two-block ADMM, one batched forward and inverse
    FFT an iteration."""

    penalties: ClassVar[dict[str, float]] = {"mu1": 0.15, "mu2": 0.003, "mu3": 0.001,
                                             "mu4": 0.005}

    def __init__(self, problem: NormalisedProblem, op: ExtendedSceneOperator, tv: float,
                 nonneg: bool, mu: dict[str, float]) -> None:
        super().__init__(problem, op, tv, nonneg, mu)
        mu1, mu2, mu3, mu4 = mu["mu1"], mu["mu2"], mu["mu3"], mu["mu4"]
        y, spectra = problem.y, problem.spectra                       # (K, C, PH, PW//2+1)
        n_kernels, channels = int(spectra.shape[0]), int(spectra.shape[1])
        self.n_kernels = n_kernels
        self.weights = op.scene_weights[:, None]                      # (K, 1, PH, PW)
        self.power = (spectra.abs() ** 2).sum(dim=0)                  # Σ_k |K̂_k|²
        self.g_gain = mu1 / (mu4 + mu1 * self.power)
        self.x_gain = 1.0 / (mu2 * finite_difference_spectrum(self.grid, y.dtype) + mu3)
        weight_power = (self.weights ** 2).sum(dim=0)                 # Σ_k V_k², (1, PH, PW)
        z_gain = 1.0 / (mu4 * weight_power + mu3)
        # Σ_k V_k (r_k + b_k) = Σ_k V_k² z_old + 2q − q_old with q = Σ_k V_k b_k
        # (b_k = H_kᵀ g), so z = z_keep·z_old + z_q·(2q − q_old) + z_x·(x − d) before the clip.
        self.z_keep, self.z_q, self.z_x = mu4 * weight_power * z_gain, mu4 * z_gain, mu3 * z_gain
        self.y_part, self.hr_part = y / (1 + mu1), mu1 / (1 + mu1)
        grid = self.grid
        self.z, self.d = self.zeros(channels, *grid), self.zeros(channels, *grid)
        self.q, self.q_old = self.zeros(channels, *grid), self.zeros(channels, *grid)
        self.c = self.zeros(2, channels, *grid)
        self.hr_view, self.a_view = torch.zeros_like(y), torch.zeros_like(y)
        self.g_hat = torch.zeros(spectra.shape[1:], dtype=spectra.dtype, device=y.device)
        self.planes = self.zeros(n_kernels + 2, channels, *grid)     # one batched rfft
        self.data_view = crop(self.planes[n_kernels], self.sensor)    # zero outside the view
        self.inverse = torch.zeros((n_kernels + 2, *self.g_hat.shape), dtype=spectra.dtype,
                                   device=y.device)
        self.hr_hat = self.inverse[n_kernels]                         # F(Σ_k H_k r_k)
        self.dx = finite_differences(self.x)

    def step(self) -> Tensor:
        mu2, mu3 = self.mu["mu2"], self.mu["mu3"]
        n, x, weights = self.n_kernels, self.x, self.weights
        # Block 1: v (in view), z, s.
        v_view = self.y_part + self.hr_part * (self.hr_view + self.a_view)
        z = (self.z_keep * self.z).addcmul_(self.z_q, 2 * self.q - self.q_old).addcmul_(
            self.z_x, x - self.d)
        if self.nonneg:
            z.clamp_min_(0)
        s = torch.nn.functional.softshrink(self.dx + self.c, self.tv / mu2)
        # Block 2: r (Sherman–Morrison per frequency) and x (Fourier-diagonal).
        torch.mul(weights, z, out=self.planes[:n])
        torch.sub(v_view, self.a_view, out=self.data_view).sub_(self.hr_view)
        torch.add(z, self.d, out=self.planes[n + 1]).mul_(mu3).add_(
            finite_differences_adjoint(s - self.c), alpha=mu2)
        f = rfft2(self.planes)
        # Σ_k K̂_k F(V_k z): the source-side model's sum before the crop, by psfkit.forward's
        # one sum of kernel-scene products (it overwrites f[0], not needed after this)
        kvz = sum_of_kernel_products(f.__getitem__, self.problem.spectra, graph=False)
        pg_old = _scale_complex(self.power, self.g_hat)
        g_hat = (self.hr_hat + f[n]).sub_(kvz).add_(pg_old)
        self.g_hat = _scale_complex(self.g_gain, g_hat, out=g_hat)
        # Σ_k K̂_k r̂_k = Σ_k K̂_k F(V_k z) − P ĝ_old + P ĝ, written straight into the inverse
        # batch (whose c2r leaves its input as it is, so it is still there next iteration).
        torch.sub(kvz, pg_old, out=self.hr_hat).add_(_scale_complex(self.power, self.g_hat))
        torch.mul(self.problem.conj, self.g_hat, out=self.inverse[:n])
        _scale_complex(self.x_gain, f[n + 1], out=self.inverse[n + 1])
        images = irfft2(self.inverse, self.grid)
        self.q_old, self.q = self.q, images[0] * weights[0]
        for j in range(1, n):
            self.q.addcmul_(images[j], weights[j])
        self.hr_view = crop(images[n], self.sensor)
        x_new = images[n + 1]
        self.dx = finite_differences(x_new)
        self.a_view += self.hr_view - v_view
        self.c += self.dx - s
        self.d += z - x_new
        self.z = z
        self.x = x_new
        return x_new


def update_rule(op: ExtendedSceneOperator) -> type[ADMMRule]:
    """The update rule of ``op``'s form."""
    if op.convention == "source":
        return SourceSideRule
    return ShiftInvariantRule if op.weights is None else SensorSideRule


def solve_tv(measurement: Tensor, op: ExtendedSceneOperator, tv: float = 1e-3,
             iterations: int = 100, nonneg: bool = True, tol: float = 0.0,
             mu: Mapping[str, float] | None = None, norm: float | None = None,
             callback: Callable[[int, float], None] | None = None) -> TVResult:
    """ADMM-TV with the scene on the padded grid, for any kernel model (module docstring).

    Parameters
    ----------
    measurement : Tensor
        ``(C, H', W')`` in the operator's dtype.
    op : ExtendedSceneOperator
        The model; its form picks the update rule (:func:`update_rule`).
    tv : float
        Relative TV weight: ``λ = tv · peak(|y|) · ‖A‖``.
    iterations : int
        Maximum iterations.
    nonneg : bool
    tol : float
        Stop once ``‖x_k − x_{k−1}‖/‖x_k‖ < tol`` (0: off).
    mu : mapping, optional
        Penalties overriding the rule's defaults (``mu1..mu3``; source side also ``mu4``).
    norm : float, optional
        ``‖A‖`` (default :func:`psfkit.forward.norm.operator_norm`).
    callback : callable, optional
        ``callback(iteration, relative_change)`` after each iteration.

    Returns
    -------
    TVResult
        ``image`` is the ``(C, PH, PW)`` padded-grid scene in the units of ``y = A x``.

    Raises
    ------
    ConfigurationError
        Negative ``tv`` or ``tol``, ``iterations < 1``, a bad or unknown penalty.
    TensorShapeError
        A measurement that does not fit the operator.
    """
    rule_type = update_rule(op)
    unknown = set(mu or {}) - set(rule_type.penalties)
    if unknown:
        raise ConfigurationError(f"unknown penalties {sorted(unknown)} for "
                                 f"{rule_type.__name__} (it has {list(rule_type.penalties)})")
    penalties = {**rule_type.penalties, **(mu or {})}
    problem = normalised_problem(measurement, op, tv, tol, iterations,
                                 tuple(penalties.values()), norm)
    rule = rule_type(problem, op, tv, nonneg, penalties)
    track = tol > 0 or callback is not None
    result = TVResult(image=rule.x, iterations=0, converged=False, operator_norm=problem.norm)
    for k in range(1, iterations + 1):
        x = rule.x
        x_new = rule.step()
        result.iterations = k
        if track and record_change(result, k, x_new, x, tol, callback):
            break
    image = rule.x.clamp_min(0) if nonneg else rule.x
    result.image = image * (problem.peak / problem.norm)
    return result
