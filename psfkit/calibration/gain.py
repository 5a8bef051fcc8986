r"""Relative illumination (gain) of each PSF and low-order fits of it.

The gain of a PSF is its energy relative to the centre PSF over the region both cover after
registration, :math:`g = \sum_\Omega p / \sum_\Omega p_0` (so a PSF partly off the sensor is not
taken for a dim one); it includes any difference in source brightness, not only vignetting.
Fits: the cosⁿ law :math:`g = A\cos^n\theta` (``A`` fitted: a law forced through 1 would turn
the reference's own brightness error into an absurd exponent), with the exponent's 1σ and
t-test against n = 0, and a quadratic in the field coordinates (what the radial law misses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from psfkit.errors import InvalidInputError
from psfkit.numerics.significance import Estimate, checked, f_test, undetermined, weighted_lstsq


def overlap_gain(reference: np.ndarray, aligned: np.ndarray, valid: np.ndarray) -> float:
    """Energy ratio of an aligned PSF to the reference over the ``(H, W)`` bool ``valid``;
    ``reference``, ``aligned``: ``(H, W)`` (channels summed), background-subtracted, same
    exposure scale."""
    ref = float(np.sum(reference, where=valid, dtype=np.float64))
    if ref <= 0:
        raise InvalidInputError("the reference PSF has no energy in the overlap region")
    return float(np.sum(aligned, where=valid, dtype=np.float64)) / ref


#: A fitted cosⁿ exponent beyond this is not a vignetting law (natural vignetting is 4;
#: microlenses and thick apertures reach about 8 to 12): shown as not determined.
EXPONENT_LIMIT = 50.0


@dataclass(frozen=True)
class GainFit:
    """Fits of the gain map: ``scale · cos^exponent(θ)`` (``estimate``: the exponent's
    :class:`~psfkit.numerics.significance.Estimate`) and a quadratic in ``(x, y)``."""

    exponent: float
    cos_rms_residual: float
    poly_coefficients: np.ndarray = field(repr=False)
    poly_terms: tuple[str, ...] = ("1", "x", "y", "x²", "xy", "y²")
    poly_rms_residual: float = 0.0
    estimate: Estimate = field(default_factory=lambda: undetermined("not fitted"))
    scale: float = 1.0

    @property
    def exponent_std(self) -> float:
        """1σ of the exponent (NaN when it is not determined)."""
        return self.estimate.sigma

    def to_dict(self) -> dict:
        return {"cos_exponent": self.exponent, "cos_exponent_std": self.exponent_std,
                "cos_scale": self.scale, "cos_rms_residual": self.cos_rms_residual,
                "estimates": {"cos_exponent": self.estimate.to_dict()},
                "note": "gains are energy ratios to the reference capture: they include any "
                        "difference in source brightness, not only vignetting",
                "poly_terms": list(self.poly_terms),
                "poly_coefficients": self.poly_coefficients.tolist(),
                "poly_rms_residual": self.poly_rms_residual}


def fit_cos_law(gains: np.ndarray, field_deg: np.ndarray, weights: np.ndarray
                ) -> tuple[Estimate, float, float]:
    """``log g = log A + n log cos θ`` by weighted least squares over the off-axis positions.

    Parameters
    ----------
    gains, field_deg, weights : numpy.ndarray
        ``(P,)`` positive gains, ``(P, 2)`` field angles ``(θx, θy)`` in degrees, ``(P,)``.

    Returns
    -------
    exponent : Estimate
        ``n`` with its residual-scaled 1σ, tested against ``n = 0``.
    scale, rms : float
        ``A`` and the RMS of ``g − A cosⁿθ`` (NaN when the fit is not possible).
    """
    t = np.tan(np.deg2rad(field_deg))
    log_cos = -0.5 * np.log1p(np.sum(t**2, axis=1))      # cos θ = 1/sqrt(1 + tan²θx + tan²θy)
    use = log_cos < -1e-9          # the reference (θ = 0) is 1 by definition, not a measurement
    n = int(use.sum())
    if n < 3 or np.ptp(log_cos[use]) <= 1e-12:
        return (undetermined(f"{n} off-axis gain(s) at distinct field angles; the cosⁿ law "
                             "needs at least 3"), math.nan, math.nan)
    design = np.column_stack([np.ones(n), log_cos[use]])
    coef, covariance, rss, dof = weighted_lstsq(design, np.log(gains[use]), weights[use])
    _, _, rss_flat, _ = weighted_lstsq(design[:, :1], np.log(gains[use]), weights[use])
    p_value = f_test(rss_flat, rss, 1, dof)
    exponent = checked(coef[1], math.sqrt(covariance[1, 1]), 0.0, p_value, EXPONENT_LIMIT)
    scale = float(np.exp(coef[0]))
    rms = float(np.sqrt(np.mean((gains - scale * np.exp(coef[1] * log_cos)) ** 2)))
    return exponent, scale, rms


def fit_gain(gains: np.ndarray, field_deg: np.ndarray | None, positions: np.ndarray,
             weights: np.ndarray | None = None) -> GainFit:
    """Fit the gain map.

    Parameters
    ----------
    gains : numpy.ndarray
        ``(N, M)`` gains (1 at the reference).
    field_deg : numpy.ndarray or None
        ``(N, M, 2)`` field angles in degrees (``None``: no cos law).
    positions : numpy.ndarray
        ``(N, M, 2)`` field coordinates of the polynomial (any unit).
    weights : numpy.ndarray, optional
        ``(N, M)``, e.g. the overlaps.
    """
    g = gains.reshape(-1).astype(np.float64)
    w = np.ones_like(g) if weights is None else np.clip(weights.reshape(-1), 0, None)
    p = positions.reshape(-1, 2).astype(np.float64)
    # NaN gains (gaps, excluded positions) and unknown positions are left out
    ok = np.isfinite(g) & (g > 0) & (w > 0) & np.isfinite(p).all(axis=1)
    estimate, scale, cos_rms = undetermined("no field angles"), math.nan, math.nan
    if field_deg is not None:
        angles = field_deg.reshape(-1, 2).astype(np.float64)
        usable = ok & np.isfinite(angles).all(axis=1)
        estimate, scale, cos_rms = fit_cos_law(g[usable], angles[usable], w[usable])
    known = np.isfinite(p).all(axis=1)
    p = p / max(float(np.max(np.abs(p[known]), initial=0.0)), 1e-30)
    x, y = p[:, 0], p[:, 1]
    design = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    if ok.sum() >= design.shape[1] and np.linalg.matrix_rank(design[ok]) == design.shape[1]:
        sw = np.sqrt(w[ok])
        coef, *_ = np.linalg.lstsq(design[ok] * sw[:, None], g[ok] * sw, rcond=None)
        poly_rms = float(np.sqrt(np.mean((design[ok] @ coef - g[ok]) ** 2)))
    else:  # too few positions (or all on one line) for a 2-D quadratic
        coef, poly_rms = np.full(6, np.nan), float("nan")
    return GainFit(exponent=estimate.value, cos_rms_residual=cos_rms, poly_coefficients=coef,
                   poly_rms_residual=poly_rms, estimate=estimate, scale=scale)
