r"""Relative illumination (gain, vignetting) of each PSF and low-order fits of it.

The gain of a PSF is its energy relative to the reference (centre) PSF, measured on the
region both PSFs cover after registration (so that a PSF partly off the sensor is not taken
for a dim one): :math:`g = \sum_\Omega p / \sum_\Omega p_0`.

Two fits summarise the map: the cosⁿ law :math:`g = \cos^n\theta` (n = 4 for natural
vignetting; microlenses and a thick aperture steepen it) and a quadratic polynomial in the
field coordinates, whose residual shows what the radial law misses (e.g. a tilted sensor).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psfkit.errors import InvalidInputError


def overlap_gain(reference: np.ndarray, aligned: np.ndarray, valid: np.ndarray) -> float:
    """Energy ratio of an aligned PSF to the reference over the pixels ``valid`` in both.

    Parameters
    ----------
    reference, aligned : numpy.ndarray
        ``(H, W)`` (e.g. the channel sum or luminance) or ``(C, H, W)``, background-subtracted,
        same exposure scale.
    valid : numpy.ndarray
        ``(H, W)`` bool.
    """
    if reference.ndim == 3:
        reference, aligned = reference.sum(axis=0), aligned.sum(axis=0)
    ref = float(np.sum(reference, where=valid, dtype=np.float64))
    if ref <= 0:
        raise InvalidInputError("the reference PSF has no energy in the overlap region")
    return float(np.sum(aligned, where=valid, dtype=np.float64)) / ref


@dataclass(frozen=True)
class GainFit:
    """Fits of the gain map: ``cos^exponent(θ)`` and a quadratic polynomial in ``(x, y)``."""

    exponent: float
    cos_rms_residual: float
    poly_coefficients: np.ndarray = field(repr=False)
    poly_terms: tuple[str, ...] = ("1", "x", "y", "x²", "xy", "y²")
    poly_rms_residual: float = 0.0

    def to_dict(self) -> dict:
        return {"cos_exponent": self.exponent, "cos_rms_residual": self.cos_rms_residual,
                "poly_terms": list(self.poly_terms),
                "poly_coefficients": self.poly_coefficients.tolist(),
                "poly_rms_residual": self.poly_rms_residual}


def fit_gain(gains: np.ndarray, field_deg: np.ndarray | None, positions: np.ndarray,
             weights: np.ndarray | None = None) -> GainFit:
    """Fit the gain map.

    Parameters
    ----------
    gains : numpy.ndarray
        ``(N, M)`` gains (1 at the reference).
    field_deg : numpy.ndarray or None
        ``(N, M, 2)`` field angles; without them the cos-law fit is skipped (NaN).
    positions : numpy.ndarray
        ``(N, M, 2)`` field coordinates for the polynomial (any unit; normalized internally).
    weights : numpy.ndarray, optional
        ``(N, M)`` weights, e.g. the overlap fraction of each position.
    """
    g = gains.reshape(-1).astype(np.float64)
    w = np.ones_like(g) if weights is None else np.clip(weights.reshape(-1), 0, None)
    p = positions.reshape(-1, 2).astype(np.float64)
    # NaN gains (gaps, excluded positions) and unknown positions are left out
    ok = np.isfinite(g) & (g > 0) & (w > 0) & np.isfinite(p).all(axis=1)
    exponent, cos_rms = float("nan"), float("nan")
    if field_deg is not None:
        t = np.tan(np.deg2rad(field_deg.reshape(-1, 2)))
        log_cos = -0.5 * np.log1p(np.sum(t**2, axis=1))      # cos θ = 1/sqrt(1 + tan²θx + tan²θy)
        use = ok & (log_cos < -1e-9)
        if use.any():
            exponent = float(np.sum(w[use] * log_cos[use] * np.log(g[use]))
                             / np.sum(w[use] * log_cos[use] ** 2))
            cos_rms = float(np.sqrt(np.mean((g[ok] - np.exp(exponent * log_cos[ok])) ** 2)))
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
    return GainFit(exponent=exponent, cos_rms_residual=cos_rms, poly_coefficients=coef,
                   poly_rms_residual=poly_rms)
