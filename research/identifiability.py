r"""How well do (scene, measurement) pairs determine the eigen-kernels? (issue 23, item 4)

Two answers for N pairs of an operator at a photon level ``P`` (the virtual bench's noise
model, Poisson–Gaussian: ``y = (Poisson(P·clip(y₀, 0)) + N(0, σ_r²)) / P``, ``σ_r`` the read
noise in electrons, so the noise variance per pixel is about ``y₀/P + σ_r²/P²``):

**Fisher information** (:func:`difference_fisher`), in the *no-crop approximation*: for the
source convention the kernels' normal operator of the uncropped, whole-grid problem is
block-diagonal in frequency (:class:`psfkit.fitting.pairs.gram.FrequencyGram`: one ``K × K`` Gram
block :math:`G(\omega)` per frequency and channel). With white noise of variance
:math:`\bar\sigma^2` (the mean of the bench's per-pixel variance) the Fisher information is
:math:`G(\omega)/(M\bar\sigma^2)` (``M`` grid pixels, unnormalised FFT). Written in the
coordinates ``(Kbase, Kv − Kbase, Kh − Kbase)`` (``T``: ``K_k = K_0 + δ_k``), the information
about the differences, ``Kbase`` a nuisance, is the Schur complement
:math:`S(\omega) = F_{\delta\delta} - F_{\delta0}F_{00}^{-1}F_{0\delta}` of
:math:`T^H G T`; its eigenvalues (per frequency and channel) are the spectrum reported, and its
inverse is the Cramér–Rao covariance: :math:`\mathbb E\lVert\hat\delta_k - \delta_k\rVert^2 =
\bar\sigma^2\sum_\omega [S(\omega)^{-1}]_{kk}` (summed over the full spectrum and the
channels). It is an approximation of the real problem in two ways: the measurement is cropped
to the sensor and the kernels live on a sensor-sized window (the exact normal operator is not
per-frequency, :mod:`psfkit.fitting.pairs.solver`), and the noise is not white (Poisson). The
Monte-Carlo says how far it is off.

**Monte-Carlo** (:func:`monte_carlo`): noise-free measurements of the scenes (``A x``, any
forward operator), several noise draws at photon level ``P``, the exact unconstrained
least-squares fit of each (:func:`psfkit.fitting.pairs.fit.fit_pairs`: no ridge, no prior, no scale,
no constraint, solved to convergence, so the estimator is linear and its mean is the
noise-free fit), and the spread over the draws of the difference kernels and of their
displacement maps (:func:`research.compare.displacement_map`, on the reference model's caustic
mask). Spreads are standard deviations over the draws (``ddof = 1``): kernels relative to the
reference difference kernels' norm, displacement maps as the RMS over the mask in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from psfkit.calibration.preprocess import luminance
from psfkit.errors import InvalidInputError
from psfkit.fitting.pairs.batches import PairBatches
from psfkit.fitting.pairs.fit import fit_pairs
from psfkit.fitting.pairs.options import PairFitOptions
from psfkit.forward.weights import get_basis
from research.compare.displacement import DisplacementMap, comparison_mask, displacement_map
from research.compare.options import CompareOptions
from research.compare.statistics import normalized_correlation, pearson


def poisson_gaussian(clean: np.ndarray, photons: float, read_noise_e: float,
                     rng: np.random.Generator) -> np.ndarray:
    """One noisy copy of noise-free measurements (the virtual bench's noise model:
    ``(Poisson(photons · clip(clean, 0)) + N(0, read_noise_e²)) / photons``)."""
    if photons <= 0:
        raise InvalidInputError(f"photons must be > 0, got {photons}")
    electrons = rng.poisson(np.clip(clean, 0, None) * photons).astype(np.float64)
    electrons += rng.normal(0.0, read_noise_e, size=clean.shape)
    return electrons / photons


def noise_variance(clean: np.ndarray, photons: float, read_noise_e: float) -> float:
    """Mean per-pixel noise variance of :func:`poisson_gaussian` (measurement units²)."""
    return float(np.mean(np.clip(clean, 0, None)) / photons + (read_noise_e / photons) ** 2)


def _difference_transform(k: int) -> np.ndarray:
    t = np.eye(k)
    t[1:, 0] = 1.0            # K_k = K_0 + δ_k
    return t


def difference_fisher(batches: PairBatches, sigma2: float) -> dict[str, Any]:
    """Fisher information about ``K_k − K_0`` in the no-crop approximation (module docstring).

    Parameters
    ----------
    batches : PairBatches
        The scenes (source convention or SI-free basis with ≥ 2 kernels).
    sigma2 : float
        Noise variance per pixel (:func:`noise_variance`).

    Returns
    -------
    dict
        ``eig_min``, ``eig_median``, ``eig_max``: eigenvalues of the Fisher information of the
        differences over frequencies and channels (per unit kernel spectrum:
        :math:`S(\\omega)/(M\\bar\\sigma^2)`); ``crb_sq`` ``{name: E‖δ̂_k − δ_k‖²}``, the
        Cramér–Rao bound on the squared error of each difference kernel (all channels).
    """
    if batches.convention != "source" or batches.n_kernels < 2:
        raise InvalidInputError("difference_fisher needs a source-side model with correction "
                                "kernels (the per-frequency blocks are exact only there)")
    g = batches.gram().matrix()                                      # (C, PH, PF, K, K)
    k = batches.n_kernels
    t = torch.as_tensor(_difference_transform(k), dtype=g.dtype)
    f = t.T @ g @ t
    f00 = f[..., :1, :1].real.clamp_min(1e-300)
    s = f[..., 1:, 1:] - f[..., 1:, :1] @ f[..., :1, 1:] / f00
    s = 0.5 * (s + s.conj().transpose(-1, -2))
    m = batches.grid[0] * batches.grid[1]
    eig = torch.linalg.eigvalsh(s).clamp_min(0) / (m * sigma2)
    # full spectrum from the half (rfft) one: interior columns count twice
    pw = batches.grid[1]
    weight = torch.full((s.shape[2],), 2.0, dtype=torch.float64)
    weight[0] = 1.0
    if pw % 2 == 0:
        weight[-1] = 1.0
    scale = float(torch.diagonal(s, dim1=-2, dim2=-1).real.mean())
    inv = torch.linalg.inv(s + 1e-14 * max(scale, 1e-300) * torch.eye(k - 1, dtype=s.dtype))
    diag = torch.diagonal(inv, dim1=-2, dim2=-1).real                # (C, PH, PF, K-1)
    crb = sigma2 * (diag * weight[None, None, :, None]).sum(dim=(0, 1, 2))
    names = get_basis(batches.basis).kernel_names
    flat = eig.flatten()
    return {"approximation": "no crop, whole-grid kernels, white noise of the mean variance",
            "eig_min": float(flat.min()), "eig_median": float(flat.median()),
            "eig_max": float(flat.max()),
            "crb_sq": {names[j + 1]: float(crb[j]) for j in range(k - 1)}}


@dataclass
class SpreadResult:
    """What :func:`monte_carlo` measured (see the module docstring). Per correction kernel
    name: ``kernel_spread`` (std over draws of ``K_k − K_0``, relative to the reference's
    ``‖K_k − K_0‖``), ``kernel_sq`` (the squared std, absolute: compare with the Cramér–Rao
    ``crb_sq``), ``ncc`` (mean difference NCC of one draw's fit against the reference),
    ``bias`` (``‖δ_clean − δ_ref‖ / ‖δ_ref‖`` of the noise-free fit), ``disp_spread_px``
    (std over draws of the displacement map, RMS over the mask), ``disp_bias_px`` (mean
    end-point error of the noise-free fit's map against the reference's), ``disp_corr``
    (mean correlation of one draw's map with the reference's) and ``ref_rms_px``."""

    draws: int
    photons: float
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    fits: list[np.ndarray] = field(default_factory=list, repr=False)


def _maps(kernels: np.ndarray, mask: np.ndarray, options: CompareOptions
          ) -> dict[int, DisplacementMap]:
    lum = np.stack([luminance(k) for k in kernels])
    return {k: displacement_map(lum[0], lum[k], mask, options.flow_method, options.smooth_px)
            for k in range(1, len(kernels))}


def fit_unconstrained(scenes: np.ndarray, measurements: np.ndarray, basis: str,
                      convention: str, tolerance: float = 1e-6) -> np.ndarray:
    """The exact, unconstrained least-squares kernels (no ridge, prior, scale or constraint)."""
    options = PairFitOptions(basis=basis, convention=convention, fit_scale=False,
                             nonneg=False, tolerance=tolerance, tikhonov=0.0, difference=0.0)
    return fit_pairs(scenes, measurements, options).kernels.astype(np.float64)


def monte_carlo(scenes: np.ndarray, clean: np.ndarray, reference: np.ndarray,
                photons: float, read_noise_e: float, draws: int, basis: str = "paper",
                convention: str = "source", seed: int = 0,
                clean_fit: np.ndarray | None = None,
                options: CompareOptions | None = None) -> SpreadResult:
    """Spread of the fitted difference kernels and displacement maps over noise draws.

    Parameters
    ----------
    scenes, clean : numpy.ndarray
        ``(N, C, H', W')`` scenes and their noise-free measurements (``A x``).
    reference : numpy.ndarray
        ``(K, C, H', W')`` reference kernels (an oracle): the unit of the relative spreads,
        the caustic mask of the displacement maps, and the reference of the biases.
    photons, read_noise_e : float
        Noise model (:func:`poisson_gaussian`).
    draws : int
        Noise realisations (≥ 2).
    clean_fit : numpy.ndarray, optional
        The noise-free fit (computed when not given; the estimator's mean).
    """
    if draws < 2:
        raise InvalidInputError("monte_carlo needs at least 2 draws for a spread")
    options = options or CompareOptions()
    rng = np.random.default_rng(seed)
    if clean_fit is None:
        clean_fit = fit_unconstrained(scenes, clean, basis, convention)
    fits = [fit_unconstrained(scenes, poisson_gaussian(clean, photons, read_noise_e, rng),
                              basis, convention) for _ in range(draws)]
    ref_lum = luminance(reference[0])
    mask = comparison_mask(ref_lum, options)
    ref_maps = _maps(reference, mask, options)
    clean_maps = _maps(clean_fit, mask, options)
    draw_maps = [_maps(f, mask, options) for f in fits]
    names = get_basis(basis).kernel_names
    out: dict[str, dict[str, float]] = {}
    for k in range(1, len(reference)):
        ref_d = reference[k] - reference[0]
        deltas = np.stack([f[k] - f[0] for f in fits])
        var = deltas.var(axis=0, ddof=1).sum()
        ref_norm = float(np.linalg.norm(ref_d))
        fields = np.stack([m[k].field for m in draw_maps])              # (D, 2, H, W)
        if mask.any():
            dvar = fields[:, :, mask].var(axis=0, ddof=1).sum(axis=0)    # per pixel |·|²
            disp_spread = float(np.sqrt(dvar.mean()))
            epe = np.sqrt(((clean_maps[k].field - ref_maps[k].field)[:, mask] ** 2).sum(0))
            disp_bias = float(epe.mean())
            corrs = [pearson(m[k].field, ref_maps[k].field, mask) for m in draw_maps]
            corr = float(np.mean(corrs))
        else:
            disp_spread = disp_bias = corr = float("nan")
        out[names[k]] = {
            "kernel_spread": float(np.sqrt(var)) / ref_norm,
            "kernel_sq": float(var),
            "ncc": float(np.mean([normalized_correlation(d, ref_d) for d in deltas])),
            "bias": float(np.linalg.norm(clean_fit[k] - clean_fit[0] - ref_d)) / ref_norm,
            "disp_spread_px": disp_spread, "disp_bias_px": disp_bias, "disp_corr": corr,
            "ref_rms_px": ref_maps[k].rms()}
    return SpreadResult(draws=draws, photons=photons, metrics=out, fits=fits)


__all__ = ["SpreadResult", "difference_fisher", "fit_unconstrained", "monte_carlo",
           "noise_variance", "poisson_gaussian"]
