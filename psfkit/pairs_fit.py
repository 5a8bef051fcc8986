r"""Forward models fitted to (scene, measurement) pairs (``psfkit fit-pairs``, ``eval-model``).

For users without a point-source grid: the kernels of a shift-invariant or eigen-kernel model
``y = A_K x`` (the forward model of :mod:`psfkit.forward`, which ekdun's operators wrap, so
the fitted model is exactly the one ekdun trains with) are estimated from pairs by regularised
least squares (in the kernel-space form :class:`~psfkit.forward.kernel_space.KernelSpaceOperator`),

.. math::

    \min_K \sum_i \lVert A_K x_i - y_i\rVert^2 + \lambda\lVert K\rVert^2
           + \mu \sum_{k\ge1}\lVert K_k - K_0\rVert^2 ,

which is linear in ``K``: with :math:`B_i: K \mapsto A_K x_i` the normal equations
:math:`(\sum_i B_i^\top B_i + \lambda I + \mu D)K = \sum_i B_i^\top y_i` are solved by
preconditioned conjugate gradients, every ``B_i`` and ``B_i^\top`` applied with real FFTs on the
padded grid (the scene spectra are computed once). The preconditioner divides each kernel's
spectrum by :math:`\bar w\,\sum_i\sum_j|\hat s_{ij}|^2 + \lambda` per frequency
(:meth:`~psfkit.forward.kernel_space.KernelSpaceOperator.precondition`), with :math:`\hat s_{ij}`
the spectra of the scenes as the kernels see them (:math:`j` runs over the one unweighted scene,
or over the K weighted scenes :math:`W_j x_i` of a source-side model) and :math:`\bar w` the
mean of the squared weight maps (1 for the SI model): the circulant part of the normal operator
for one kernel with a spatially averaged weight; it ignores the coupling between kernels and
the difference prior.
``λ`` and ``μ`` are relative to the mean of :math:`\sum_i|\hat x_i|^2`, so they do not depend
on the data's units. Datasets whose ground truth was normalised image by image (the DiffuserCam
Mirflickr set: each lensed image scaled to max 1) get one scale per pair, estimated in a few
alternating rounds (``fit_scale``).

By default the kernels are then made physical: the final solve continues, warm-started from the
CG solution, by accelerated projected gradient under non-negativity and optionally a support
and per-kernel energies (:mod:`psfkit.pairs_constraints`; ``PairFitOptions.nonneg``,
``support``, ``energy``). :meth:`PairFit.physics` is what the kernel file records about them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.eigen import _difference_prior as difference_prior
from psfkit.errors import InvalidInputError
from psfkit.forward.convolution import eigen_kernel_forward, kernel_spectra, zero_workspace
from psfkit.forward.geometry import padded_shape
from psfkit.forward.kernel_space import KernelSpaceOperator
from psfkit.io.read_options import ReadOptions
from psfkit.kernelfile import KernelModel
from psfkit.pairs_constraints import auto_support, kernel_summary, projected_fit
from psfkit.pairs_options import PairFitOptions
from psfkit.resample import bin_mean
from psfkit.weights import get_basis


def _per_channel_dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(dim=(0, 2, 3))                                        # (C,)


@dataclass
class PairFit:
    """Result of :func:`fit_pairs`: kernels ``(K, C, Hk, Wk)``, per-pair scales and relative
    training errors, and the solver's history."""

    kernels: np.ndarray = field(repr=False)
    basis: str
    convention: str
    scales: np.ndarray
    training_error: np.ndarray
    history: list[dict[str, Any]]
    options: PairFitOptions
    support: np.ndarray | None = field(default=None, repr=False)

    def physics(self) -> dict[str, Any]:
        """The constraints imposed and what the kernels are: energies ``[K][C]``, support
        fraction, negative and non-finite pixel counts (recorded in the kernel file)."""
        o = self.options
        return {"constraints": {"nonneg": o.nonneg, "support": o.support,
                                "energy": o.energy},
                **kernel_summary(self.kernels)}

    def kernel_model(self, provenance: dict[str, Any] | None = None,
                     read_options: ReadOptions | None = None) -> KernelModel:
        """The kernel file content; ``read_options``: how the fitted pairs were read
        (:meth:`psfkit.io.pairs.PairSet.read_options`), recorded for the model's users."""
        channels = ("L",) if self.kernels.shape[1] == 1 else ("R", "G", "B")
        return KernelModel(kernels=self.kernels, basis=self.basis, convention=self.convention,
                           sensor_shape=self.kernels.shape[-2:], channels=channels,
                           scene_padding=self.options.scene_padding,
                           normalization="fitted in the pairs' own units: y = A x",
                           provenance=provenance or {}, read_options=read_options)


def downsample_pairs(scenes: np.ndarray, measurements: np.ndarray, factor: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Average ``factor × factor`` blocks of ``(N, C, H, W)`` scenes and measurements
    (trailing rows/columns dropped); the forward model keeps its form at the coarser pitch."""
    if factor == 1:
        return scenes, measurements

    def binned(a: np.ndarray) -> np.ndarray:
        h, w = a.shape[-2:]
        hh, ww = h // factor, w // factor
        if hh < 4 or ww < 4:
            raise InvalidInputError(f"downsampling {h}x{w} pairs by {factor} leaves too few "
                                    "pixels")
        return bin_mean(a, factor).astype(np.float32)

    return binned(scenes), binned(measurements)


def fit_pairs(scenes: np.ndarray, measurements: np.ndarray,
              options: PairFitOptions | None = None, initial: np.ndarray | None = None,
              dtype: torch.dtype = torch.float32, device: str = "cpu",
              progress: bool = False, support_mask: np.ndarray | None = None) -> PairFit:
    """Fit a forward model to ``(N, C, H, W)`` scenes and measurements.

    Parameters
    ----------
    scenes, measurements : numpy.ndarray
        ``(N, C, H', W')`` each (scene and measurement of a pair have the sensor's size).
    options : PairFitOptions
    initial : numpy.ndarray, optional
        ``(K, C, Hk, Wk)`` starting kernels (e.g. a shift-invariant fit for an EK model).
    support_mask : numpy.ndarray, optional
        ``(H', W')`` footprint outside which the kernels are zero (``options.support ==
        "mask"``; nonzero = inside).

    Raises
    ------
    InvalidInputError
        Mismatched shapes, no pairs, a support mask missing or of the wrong size, or an
        energy constraint that a non-negative kernel cannot meet (a sum <= 0).
    """
    options = options or PairFitOptions()
    if scenes.shape != measurements.shape or scenes.ndim != 4 or len(scenes) == 0:
        raise InvalidInputError(f"scenes {scenes.shape} and measurements {measurements.shape} "
                                "must both be (N, C, H, W) with N >= 1")
    if (options.support == "mask") != (support_mask is not None):
        raise InvalidInputError("a support mask is given exactly when options.support is "
                                f"'mask' (support {options.support!r})")
    if support_mask is not None and tuple(support_mask.shape) != tuple(scenes.shape[-2:]):
        raise InvalidInputError(f"the support mask is {support_mask.shape[0]}x"
                                f"{support_mask.shape[1]}, the kernels "
                                f"{scenes.shape[-2]}x{scenes.shape[-1]}")
    x = torch.as_tensor(scenes, dtype=dtype, device=device)
    y = torch.as_tensor(measurements, dtype=dtype, device=device)
    n, c, h, w = x.shape
    kernel_shape = (h, w)
    n_kernels = get_basis(options.basis).n_kernels
    # D of Σ_{k≥1}‖K_k − K_0‖²/2 (the one definition, shared with fit-eigen), (K, K)
    prior = torch.as_tensor(difference_prior(n_kernels), dtype=dtype, device=device)
    scales = torch.ones(n, dtype=dtype, device=device)
    if initial is None and n_kernels > 1 and options.seed_with_si:
        seed = fit_pairs(scenes, measurements,
                         dataclasses.replace(options, basis="si", iterations=None,
                                             nonneg=False, support="none", energy="free"),
                         dtype=dtype, device=device, progress=progress)
        initial = np.repeat(seed.kernels, n_kernels, axis=0)
        scales = torch.as_tensor(seed.scales, dtype=dtype, device=device)
    kernels = torch.zeros((n_kernels, c, *kernel_shape), dtype=dtype, device=device) \
        if initial is None else torch.as_tensor(initial, dtype=dtype, device=device).clone()
    history: list[dict[str, Any]] = []
    # Scale rounds need only a rough kernel estimate (warm-started each time); the final solve
    # with the scales fixed gets the full iteration count.
    scale_rounds = options.rounds - 1 if options.fit_scale else 0
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=scale_rounds * options.scale_iterations + options.final_iterations,
                   unit="it", leave=False, desc=f"fit {options.basis}")
    round_index = 0
    while True:
        final_round = round_index >= scale_rounds
        op = KernelSpaceOperator(x * scales[:, None, None, None], options.basis,
                                 options.convention, kernel_shape, options.scene_padding)
        reference = float(op.power.mean())
        lam = options.tikhonov * reference
        mu = options.difference * reference

        def normal(k: Tensor, op: KernelSpaceOperator = op, lam: float = lam,
                   mu: float = mu) -> Tensor:
            out = op.adjoint(op.forward(k)) + lam * k
            if n_kernels == 1:
                return out
            return out + mu * torch.tensordot(prior, k, dims=([1], [0]))

        rhs = op.adjoint(y)
        kernels, info = _conjugate_gradients(
            normal, rhs, kernels, lambda r, op=op, lam=lam: op.precondition(r, lam),
            options.final_iterations if final_round else options.scale_iterations,
            options.tolerance, bar)
        info["round"] = round_index
        history.append(info)
        if final_round:
            break
        # the model is linear in the scene: the unscaled prediction is the scaled one / scale
        prediction = op.forward(kernels) / scales[:, None, None, None]
        num = (prediction * y).sum(dim=(1, 2, 3))
        den = (prediction * prediction).sum(dim=(1, 2, 3)).clamp_min(1e-30)
        new = num / den
        new = new / new.mean()                       # the overall scale stays in the kernels
        if float((new - scales).abs().max()) < 1e-4:
            scale_rounds = round_index + 1           # converged: go to the final solve
        scales = new
        round_index += 1
    support = None
    if options.constrained:
        kernels, support, info = _constrained_solve(normal, rhs, kernels, options,
                                                    support_mask, progress)
        history.append(info)
    if bar is not None:
        bar.close()
    residual = op.forward(kernels) - y
    errors = residual.pow(2).sum(dim=(1, 2, 3)).sqrt() / y.pow(2).sum(dim=(1, 2, 3)).sqrt()
    return PairFit(kernels=kernels.cpu().numpy(), basis=options.basis,
                   convention=options.convention, scales=scales.cpu().numpy(),
                   training_error=errors.cpu().numpy(), history=history, options=options,
                   support=support)


def _constrained_solve(normal: Any, rhs: Tensor, unconstrained: Tensor,
                       options: PairFitOptions, support_mask: np.ndarray | None,
                       progress: bool) -> tuple[Tensor, np.ndarray | None, dict[str, Any]]:
    """The final solve under ``options``' constraints, warm-started from the unconstrained
    (CG) kernels, whose base kernel also gives the automatic support and the energies."""
    support = None
    if options.support == "auto":
        support = auto_support(unconstrained[0].cpu().numpy(), options.support_threshold)
    elif options.support == "mask":
        support = np.asarray(support_mask) != 0
    energy = None
    if options.energy == "fit":
        energy = unconstrained.sum(dim=(2, 3))
    elif options.energy == "base":
        energy = unconstrained[0].sum(dim=(1, 2))[None].expand(unconstrained.shape[0], -1)
    if energy is not None and options.nonneg and bool((energy <= 0).any()):
        raise InvalidInputError(f"energy {options.energy!r}: the unconstrained fit has a "
                                "kernel with sum <= 0, which no non-negative kernel matches")
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=options.final_projected_iterations, unit="it", leave=False,
                   desc="projected fit")
    mask = None if support is None else torch.as_tensor(support, device=rhs.device)
    kernels, info = projected_fit(normal, rhs, unconstrained,
                                  options.final_projected_iterations,
                                  options.nonneg, mask, energy, bar=bar)
    if bar is not None:
        bar.close()
    info["support_fraction"] = 1.0 if support is None else float(support.mean())
    return kernels, support, info


def _conjugate_gradients(apply: Any, rhs: Tensor, start: Tensor, precondition: Any,
                         iterations: int, tolerance: float, bar: Any = None
                         ) -> tuple[Tensor, dict[str, Any]]:
    """Preconditioned CG, independent per colour channel (per-channel step sizes)."""
    x = start.clone()
    r = rhs - apply(x)
    z = precondition(r)
    p = z.clone()
    rz = _per_channel_dot(r, z)
    norm_rhs = _per_channel_dot(rhs, rhs).sqrt().clamp_min(1e-30)
    done = 0
    relative = float("nan")
    while done < iterations:
        done += 1
        ap = apply(p)
        alpha = rz / _per_channel_dot(p, ap).clamp_min(1e-30)
        x += alpha[None, :, None, None] * p
        r -= alpha[None, :, None, None] * ap
        relative = float((_per_channel_dot(r, r).sqrt() / norm_rhs).max())
        if bar is not None:
            bar.update(1)
        if relative < tolerance:
            break
        z = precondition(r)
        rz_new = _per_channel_dot(r, z)
        beta = rz_new / rz.clamp_min(1e-30)
        p = z + beta[None, :, None, None] * p
        rz = rz_new
    return x, {"iterations": done, "relative_residual": relative}


def predict(model: KernelModel, scenes: np.ndarray, dtype: torch.dtype = torch.float32
            ) -> np.ndarray:
    """Measurements ``(N, C, H', W')`` that a kernel-file model predicts for ``scenes``."""
    if tuple(scenes.shape[-2:]) != tuple(model.sensor_shape):
        raise InvalidInputError(f"scenes are {scenes.shape[-2]}x{scenes.shape[-1]} but the "
                                f"model's sensor is {model.sensor_shape[0]}x"
                                f"{model.sensor_shape[1]}")
    if scenes.shape[1] != len(model.channels):
        raise InvalidInputError(f"scenes have {scenes.shape[1]} channel(s), the model "
                                f"{len(model.channels)}")
    grid = padded_shape(tuple(model.sensor_shape), model.scene_padding)
    with torch.no_grad():
        x = torch.as_tensor(scenes, dtype=dtype)
        spectra = kernel_spectra(torch.as_tensor(model.kernels, dtype=dtype), grid)
        weights = torch.as_tensor(model.weight_maps(), dtype=dtype)
        return eigen_kernel_forward(x, spectra, weights, grid, model.convention,
                                    zero_workspace(x, grid)).numpy()


def relative_errors(prediction: np.ndarray, measurements: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pair ``‖y − A x‖/‖y‖`` as predicted (``raw``) and with the best scale per pair
    (``scaled``: what remains once an unknown per-image normalisation is allowed for)."""
    p = prediction.reshape(len(prediction), -1).astype(np.float64)
    y = measurements.reshape(len(measurements), -1).astype(np.float64)
    norm = np.linalg.norm(y, axis=1)
    raw = np.linalg.norm(p - y, axis=1) / norm
    scale = np.sum(p * y, axis=1) / np.maximum(np.sum(p * p, axis=1), 1e-30)
    scaled = np.linalg.norm(scale[:, None] * p - y, axis=1) / norm
    return {"raw": raw, "scaled": scaled, "scale": scale}


def leave_one_out(scenes: np.ndarray, measurements: np.ndarray, options: PairFitOptions,
                  progress: bool = False, support_mask: np.ndarray | None = None
                  ) -> dict[str, Any]:
    """Held-out errors: each pair predicted by the model fitted on all the others."""
    n = len(scenes)
    if n < 2:
        raise InvalidInputError("leave-one-out needs at least two pairs")
    raw, scaled = np.zeros(n), np.zeros(n)
    indices: Any = range(n)
    if progress:
        from tqdm.auto import tqdm

        indices = tqdm(indices, desc=f"leave-one-out ({options.basis})", unit="fit")
    for i in indices:
        keep = np.arange(n) != i
        fit = fit_pairs(scenes[keep], measurements[keep], options,
                        support_mask=support_mask)
        errors = relative_errors(predict(fit.kernel_model(), scenes[i:i + 1]),
                                 measurements[i:i + 1])
        raw[i], scaled[i] = errors["raw"][0], errors["scaled"][0]
    return {"raw": raw, "scaled": scaled,
            "mean_raw": float(np.mean(raw)), "mean_scaled": float(np.mean(scaled)),
            "rms_raw": float(math.sqrt(np.mean(raw**2))),
            "rms_scaled": float(math.sqrt(np.mean(scaled**2)))}
