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
``P``; ``P`` only sets how fast. (Scaling ``P`` by the fraction of outputs each offset sees, a
diagonal correction for the crop, was tried and slowed convergence slightly.) On the 64 × 64
virtual bench (96 pairs, paper basis) it reaches a relative residual of 1e-6 in 60 (source)
and 92 (sensor) iterations, against 188 and 127 with the scalar per-kernel preconditioner of
the earlier solver.

Non-negativity (and a support) is imposed afterwards by projected Newton-CG
(:func:`psfkit.fitting.pairs.constraints.projected_newton`), the one
non-negative solver, warm-started from the converged unconstrained solution and with the same
streaming normal operator.

Library entry points: :class:`PairBatches` (the pairs, in batches, with optional per-pair
scales), :class:`FrequencyGram` (the per-frequency blocks, one pass) and
:func:`solve_normal_equations` (PCG to a tolerance). The non-negative solve built on them,
projected Newton-CG, is :func:`psfkit.fitting.pairs.constraints.projected_newton`.
:func:`psfkit.fitting.pairs.fit.fit_pairs` and
the research studies' operator oracle (``research/oracles.py``) are built on them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.errors import InvalidInputError
from psfkit.forward.convolution import embed_kernel, extract_kernel, kernel_spectra
from psfkit.forward.fft import irfft2
from psfkit.forward.kernel_space import KernelSpaceOperator, linear_convolution_grid
from psfkit.forward.weights import get_basis

#: Default bytes of scene spectra kept between passes (beyond it, they are recomputed per
#: batch in every pass: bounded memory, a few more FFTs).
DEFAULT_CACHE_BYTES = 3 * 2**29
#: Most pairs per batch of the streaming passes.
DEFAULT_BATCH = 16
#: On the CPU a batch's largest temporary (its scene spectra times a residual's) is kept under
#: glibc's largest reuse threshold (:mod:`psfkit.cli.allocator`): a larger one is served with fresh
#: ``mmap`` pages and page-faulted in on every pass (measured at 128², 96 pairs: 16 pairs per
#: batch 0.21 s a pass, half of it system time; 8 pairs 0.105 s, none).
BATCH_BYTES = 24 * 2**20

MeasurementSource = Callable[[int, int], np.ndarray | Tensor]


def difference_matrix(n_kernels: int) -> np.ndarray:
    """``D`` of :math:`\\tfrac12\\sum_{k\\ge1}\\lVert K_k - K_0\\rVert^2 = \\tfrac12 K^\\top D K`
    (``(K, K)``; the one definition, shared with :mod:`psfkit.fitting.grid.eigen`)."""
    from psfkit.fitting.grid.eigen import _difference_prior

    return _difference_prior(n_kernels)


def _per_channel_dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(dim=(0, 2, 3))                                        # (C,)


def auto_batch_size(bytes_per_pair: int, device: str = "cpu") -> int:
    """Pairs per batch: on the CPU as many as keep a batch's spectra under ``BATCH_BYTES``
    (at least 1, at most ``DEFAULT_BATCH``); elsewhere ``DEFAULT_BATCH``."""
    if str(device).split(":")[0] != "cpu":
        return DEFAULT_BATCH
    return int(min(DEFAULT_BATCH, max(1, BATCH_BYTES // max(1, bytes_per_pair))))


class PairBatches:
    """The scenes of a pairs fit, visited in batches, with their kernel-space operators.

    Parameters
    ----------
    scenes : numpy.ndarray or Tensor
        ``(N, C, H', W')``.
    basis, convention : str
        The eigen-kernel model (``"si"`` for one kernel).
    kernel_shape : (int, int)
        ``(Hk, Wk)`` (at most the sensor size).
    scene_padding : int
        Padding factor of the model (the grid is the linear-convolution grid, at most that).
    batch_size : int, optional
        Pairs per batch (memory of one batch's spectra: ``batch × K × C × grid`` complex).
        Default: :func:`auto_batch_size`.
    cache_bytes : int
        Keep the operators (scene spectra) of the first batches between passes, as many as
        fit in this many bytes; every pass recomputes the others (``0``: never cache).
        :meth:`astype`'s twin has a budget of its own.
    dtype, device
        Working precision and device of the operators (float64 for an oracle).
    """

    def __init__(self, scenes: np.ndarray | Tensor, basis: str, convention: str,
                 kernel_shape: tuple[int, int], scene_padding: int = 2,
                 batch_size: int | None = None, cache_bytes: int = DEFAULT_CACHE_BYTES,
                 dtype: torch.dtype = torch.float64, device: str = "cpu") -> None:
        if scenes.ndim != 4 or len(scenes) == 0:
            raise InvalidInputError(f"scenes must be (N, C, H, W) with N >= 1, got "
                                    f"{tuple(scenes.shape)}")
        self.scenes = scenes
        self.n, self.channels, h, w = (int(s) for s in scenes.shape)
        self.sensor = (h, w)
        self.basis, self.convention = basis, convention
        self.kernel_shape = (int(kernel_shape[0]), int(kernel_shape[1]))
        self.scene_padding = scene_padding
        self.n_kernels = get_basis(basis).n_kernels
        self.grid = linear_convolution_grid(self.sensor, self.kernel_shape, scene_padding)
        self.dtype, self.device = dtype, device
        self.cache_bytes = cache_bytes
        self.scales = torch.ones(self.n, dtype=dtype, device=device)
        per_pair = (self.n_kernels if basis != "si" and convention == "source" else 1) \
            * self.channels * self.grid[0] * (self.grid[1] // 2 + 1) \
            * (16 if dtype == torch.float64 else 8)
        self.batch_size = max(1, int(batch_size)) if batch_size is not None \
            else auto_batch_size(per_pair, device)
        # as many batches as fit in ``cache_bytes`` are kept (the first ones): with more pairs
        # than fit, the rest are recomputed in every pass, and the kept ones still save their
        # FFTs (384 pairs of 128²: 1.8 GB of float64 spectra against a 1.5 GiB budget)
        self._per_pair = per_pair
        self._cache: dict[int, KernelSpaceOperator] = {}
        self._cached_pairs = 0
        self.passes = 0
        #: Pairs that the passes visit (a cross-validation fold's, :meth:`only`); None: all.
        self.active: Tensor | None = None

    def astype(self, dtype: torch.dtype) -> PairBatches:
        """The same pairs, batches and scales in another precision, with a cache of its own
        (e.g. float32 Hessian products for :func:`projected_newton`)."""
        twin = PairBatches(self.scenes, self.basis, self.convention, self.kernel_shape,
                           self.scene_padding, None, self.cache_bytes, dtype, self.device)
        twin.scales = self.scales.to(dtype)
        return twin

    def ranges(self) -> Iterator[tuple[int, int]]:
        """``(start, stop)`` of every batch."""
        for start in range(0, self.n, self.batch_size):
            yield start, min(start + self.batch_size, self.n)

    def operator(self, start: int, stop: int) -> KernelSpaceOperator:
        """The (unscaled) kernel-space operator of pairs ``start:stop`` (cached if allowed)."""
        if start in self._cache:
            return self._cache[start]
        x = torch.as_tensor(self.scenes[start:stop], dtype=self.dtype, device=self.device)
        op = KernelSpaceOperator(x, self.basis, self.convention, self.kernel_shape,
                                 self.scene_padding)
        if op.grid != self.grid:                       # one grid for every batch
            raise AssertionError("batch grid differs")  # pragma: no cover
        if (self._cached_pairs + stop - start) * self._per_pair <= self.cache_bytes:
            self._cache[start] = op
            self._cached_pairs += stop - start
        return op

    @property
    def cached_pairs(self) -> int:
        """Pairs whose operators are kept between passes (at most ``cache_bytes`` of them)."""
        return self._cached_pairs

    @contextmanager
    def only(self, active: Tensor | np.ndarray) -> Iterator[PairBatches]:
        """Within the ``with`` block every pass visits only the pairs where ``active``
        (``(N,)`` bool) is true: the normal operator, right-hand side, Gram blocks and
        residuals of a cross-validation fold's training (or held-out) pairs, from the same
        cached scene spectra (no FFT of a scene is taken again)."""
        previous = self.active
        self.active = torch.as_tensor(np.asarray(active, dtype=bool), device=self.device)
        try:
            yield self
        finally:
            self.active = previous

    def batches(self) -> Iterator[tuple[int, int, KernelSpaceOperator, Tensor]]:
        """One pass: ``(start, stop, operator, scales)`` per batch; with :attr:`active` set,
        per run of consecutive active pairs within a batch (its operator a view of the
        batch's scene spectra: nothing is copied)."""
        self.passes += 1
        for start, stop in self.ranges():
            if self.active is None or bool(self.active[start:stop].all()):
                yield start, stop, self.operator(start, stop), self.scales[start:stop]
                continue
            for a, b in _runs(self.active[start:stop].tolist()):
                yield (start + a, start + b, self.operator(start, stop).subset(slice(a, b)),
                       self.scales[start + a:start + b])

    def measurement(self, source: np.ndarray | Tensor | MeasurementSource, start: int,
                    stop: int) -> Tensor:
        """The measurements of pairs ``start:stop`` (a batch, or a run of one)."""
        y = source(start, stop) if callable(source) else source[start:stop]
        return torch.as_tensor(y, dtype=self.dtype, device=self.device)

    # -------------------------------------------------------------------- operators
    def forward(self, kernels: Tensor) -> Iterator[tuple[int, int, Tensor]]:
        """``(start, stop, s_i B_i K)`` per batch (one pass)."""
        for start, stop, op, s in self.batches():
            yield start, stop, op.forward(kernels) * s[:, None, None, None]

    def normal(self, kernels: Tensor) -> Tensor:
        r""":math:`\sum_i s_i^2 B_i^\top B_i K` (one pass over the pairs, exact: crop and
        weights included)."""
        out = torch.zeros_like(kernels)
        for _start, _stop, op, s in self.batches():
            out += op.adjoint(op.forward(kernels) * (s * s)[:, None, None, None])
        return out

    def rhs(self, measurements: np.ndarray | Tensor | MeasurementSource) -> Tensor:
        r""":math:`\sum_i s_i B_i^\top y_i`; ``measurements`` is an ``(N, C, H', W')`` array or a
        callable ``(start, stop) → (stop − start, C, H', W')`` (made on the fly)."""
        out: Tensor | None = None
        for start, stop, op, s in self.batches():
            y = self.measurement(measurements, start, stop)
            term = op.adjoint(y * s[:, None, None, None])
            out = term if out is None else out + term
        assert out is not None
        return out

    def gram(self) -> FrequencyGram:
        """The per-frequency ``K × K`` blocks of the scaled scenes (one pass)."""
        gram = FrequencyGram(self)
        for _start, _stop, op, s in self.batches():
            gram.add(op, s)
        return gram

    def residual_norms(self, kernels: Tensor,
                       measurements: np.ndarray | Tensor | MeasurementSource
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per pair ``‖s_i B_i K − y_i‖``, ``‖y_i‖``, and the per-pair products
        ``⟨B_i K, y_i⟩`` and ``‖B_i K‖²`` of the unscaled prediction (for the scales)."""
        err = torch.zeros(self.n, dtype=self.dtype, device=self.device)
        norm, num, den = err.clone(), err.clone(), err.clone()
        for start, stop, op, s in self.batches():
            p = op.forward(kernels)
            y = self.measurement(measurements, start, stop)
            err[start:stop] = (p * s[:, None, None, None] - y).pow(2).sum(dim=(1, 2, 3)).sqrt()
            norm[start:stop] = y.pow(2).sum(dim=(1, 2, 3)).sqrt()
            num[start:stop] = (p * y).sum(dim=(1, 2, 3))
            den[start:stop] = p.pow(2).sum(dim=(1, 2, 3))
        return err, norm, num, den


def _runs(active: list[bool]) -> list[tuple[int, int]]:
    """``(start, stop)`` of every run of consecutive ``True``."""
    runs, begin = [], None
    for i, on in enumerate([*active, False]):
        if on and begin is None:
            begin = i
        elif not on and begin is not None:
            runs.append((begin, i))
            begin = None
    return runs


class FrequencyGram:
    r"""Per-frequency ``K × K`` Gram blocks of the weighted scenes, accumulated batch by batch.

    ``blocks`` is ``(C, PH, PW//2 + 1, K, K)`` complex128 (Hermitian per frequency). Source
    side (and SI): :math:`\sum_i s_i^2\,\overline{\hat S_{ik}}\hat S_{il}` — exactly the normal
    operator of the uncropped, whole-grid problem. Sensor side: :math:`m_{kl}\sum_i
    s_i^2|\hat x_i|^2` with :math:`m_{kl}` the mean of :math:`W_kW_l` over the sensor (an
    approximation; see the module docstring).
    """

    def __init__(self, batches: PairBatches) -> None:
        self.grid, self.sensor = batches.grid, batches.sensor
        self.kernel_shape = batches.kernel_shape
        self.n_kernels = batches.n_kernels
        self.convention = batches.convention
        self.basis = batches.basis
        self.channels = batches.channels
        self.device = batches.device
        freq = (self.grid[0], self.grid[1] // 2 + 1)
        k = self.n_kernels
        self.blocks = torch.zeros((self.channels, *freq, k, k), dtype=torch.complex128,
                                  device=self.device)
        self._power: Tensor | None = None
        self.mean_products = np.ones((1, 1))
        if self.basis != "si":
            w = get_basis(self.basis).maps(self.sensor).astype(np.float64)     # (K, H, W)
            self.mean_products = np.einsum("khw,lhw->kl", w, w) / (w.shape[1] * w.shape[2])

    def add(self, op: KernelSpaceOperator, scales: Tensor) -> None:
        """Add one batch (its operator's scene spectra, times the scales)."""
        spectra = op.scene_spectra.to(torch.complex128)              # (b, K or 1, C, F...)
        s2 = (scales.to(torch.float64) ** 2)[:, None, None, None, None]
        if spectra.shape[1] == 1:
            power = (spectra[:, 0].abs() ** 2 * s2[:, 0]).sum(dim=0)         # (C, F...)
            self._power = power if self._power is None else self._power + power
            return
        weighted = spectra * s2
        self.blocks += torch.einsum("bkcuv,blcuv->cuvkl", spectra.conj(), weighted)

    def matrix(self) -> Tensor:
        """The blocks ``(C, PH, PW//2+1, K, K)`` (sensor side and SI: from the summed power)."""
        if self._power is not None:
            m = torch.as_tensor(self.mean_products, dtype=torch.complex128, device=self.device)
            return self._power[..., None, None].to(torch.complex128) * m
        return self.blocks

    def reference_power(self) -> float:
        """Mean over frequencies and channels of the summed power of the scene spectra the
        kernels see (the scenes; source side: the K weighted scenes, summed): the unit of
        ``--tikhonov`` and ``--difference``."""
        if self._power is not None:
            return float(self._power.mean())
        return float(torch.diagonal(self.blocks, dim1=-2, dim2=-1).real.sum(-1).mean())

    def inverse(self, tikhonov: float, difference: float, floor: float = 1e-12) -> Tensor:
        """``[G(ω) + λ I + μ D + ε]^{-1}`` per frequency and channel; ``ε`` (``floor`` times the
        mean trace) keeps an unexcited frequency from dividing by zero (preconditioner only)."""
        k = self.n_kernels
        if self._power is not None and k == 1:           # one kernel: a division
            eps = floor * max(float(self._power.mean()), 1e-300)
            return (1.0 / (self._power + (tikhonov + eps))).to(torch.complex128)[..., None,
                                                                                  None]
        g = self.matrix()
        eye = torch.eye(k, dtype=torch.complex128, device=self.device)
        reg = tikhonov * eye + difference * torch.as_tensor(
            difference_matrix(k), dtype=torch.complex128, device=self.device)
        scale = float(torch.diagonal(g, dim1=-2, dim2=-1).real.mean())
        eps = floor * max(scale, 1e-300)
        return torch.linalg.inv(g + reg + eps * eye)

    def preconditioner(self, tikhonov: float, difference: float
                       ) -> Callable[[Tensor], Tensor]:
        """``P`` of the module docstring, a callable on ``(K, C, Hk, Wk)`` residuals, applied
        in the residual's precision (a float32 solve gets float32 FFTs: it is only a
        preconditioner)."""
        # (K, K, C, PH, PW//2+1): one multiply-add per block entry beats a batched matmul of
        # 3 x 3 matrices over the frequencies
        inverses = {torch.float64: self.inverse(tikhonov, difference).permute(3, 4, 0, 1, 2)
                    .contiguous()}

        def apply(r: Tensor) -> Tensor:
            if r.dtype not in inverses:
                inverses[r.dtype] = inverses[torch.float64].to(
                    torch.complex64 if r.dtype == torch.float32 else torch.complex128)
            inv = inverses[r.dtype]
            spectra = kernel_spectra(r, self.grid)
            solved = torch.stack([sum(inv[k, j] * spectra[j] for j in range(len(inv)))
                                  for k in range(len(inv))])
            return extract_kernel(irfft2(solved, self.grid), self.kernel_shape)

        return apply


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
        the system solved: ``"normal"``, ``"rhs"``, ``"precondition"``, ``"batches"``.
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
                           "batches": batches}


__all__ = [
    "BATCH_BYTES",
    "DEFAULT_BATCH",
    "DEFAULT_CACHE_BYTES",
    "FrequencyGram",
    "PairBatches",
    "SolveInfo",
    "auto_batch_size",
    "difference_matrix",
    "embed_kernel",
    "regularised_normal",
    "solve_kernels",
    "solve_normal_equations",
]
