"""The map from field position to PSF shift (:func:`fit_shift_map`): an affine least-squares
fit decomposed into magnification, rotation and shear, with the 1σ and significance of its
magnification, rotation and non-linear part (distortion). Shift signs: as in
:mod:`psfkit.calibration.registration`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg

from psfkit.errors import InvalidInputError
from psfkit.numerics.significance import Estimate, checked, f_test, undetermined, weighted_lstsq

#: Highest polynomial degree of the shift map fitted to test for non-linear distortion.
DISTORTION_DEGREE = 3


@dataclass(frozen=True)
class ShiftMapFit:
    """Affine fit ``shift = A · p + t`` of PSF shifts against field positions ``p``.

    ``A = R(rotation) · P`` (polar decomposition; a lensless camera has ``A ≈ −m·I``, rotation
    ≈ 180°). ``residuals`` ``(N, M, 2)`` px: distortion plus registration error. ``estimates``
    (:class:`~psfkit.numerics.significance.Estimate`): ``"magnification"`` (null 0),
    ``"rotation_deg"`` (null: the nearer of 0° and 180°) and ``"distortion_rms_px"``, the
    debiased RMS of a degree-``distortion_degree`` polynomial map minus the affine one (null 0,
    F-test).
    """

    matrix: np.ndarray
    offset: np.ndarray
    field_units: str
    rotation_deg: float
    magnification_u: float
    magnification_v: float
    shear: float
    mirrored: bool
    residuals: np.ndarray = field(repr=False)
    estimates: dict[str, Estimate] = field(default_factory=dict, repr=False)
    distortion_degree: int = 0

    @property
    def magnification(self) -> float:
        """Mean magnification ``sqrt(det P)`` (sensor px per field unit)."""
        return float(np.sqrt(max(self.magnification_u * self.magnification_v - self.shear**2,
                                 0.0)))

    @property
    def rms_residual(self) -> float:
        return float(np.sqrt(np.nanmean(np.sum(self.residuals**2, axis=-1))))

    @property
    def distortion(self) -> Estimate:
        """The non-linear part of the map (``estimates["distortion_rms_px"]``)."""
        return self.estimates.get("distortion_rms_px", undetermined("not fitted"))

    def to_dict(self) -> dict:
        out = {"field_units": self.field_units, "matrix": self.matrix.tolist(),
               "offset_px": self.offset.tolist(), "rotation_deg": self.rotation_deg,
               "magnification": self.magnification, "magnification_u": self.magnification_u,
               "magnification_v": self.magnification_v, "shear": self.shear,
               "mirrored": self.mirrored, "rms_residual_px": self.rms_residual}
        if self.estimates:
            out["estimates"] = {k: e.to_dict() for k, e in self.estimates.items()}
            out["distortion_degree"] = self.distortion_degree
        return out


def fit_shift_map(positions: np.ndarray, shifts: np.ndarray, field_units: str,
                  weights: np.ndarray | None = None, resolution_px: float = 0.0
                  ) -> ShiftMapFit:
    """Least-squares affine map from field positions to PSF shifts (:class:`ShiftMapFit`).

    Parameters
    ----------
    positions, shifts : numpy.ndarray
        ``(N, M, 2)`` field coordinates ``(x, y)`` (in ``field_units``) and ``(du, dv)``; NaN
        positions are left out (NaN residual).
    weights : numpy.ndarray, optional
        ``(N, M)`` non-negative weights.
    resolution_px : float
        Registration step: its rounding error (``resolution/√12``) enters the non-linear
        part's σ, so no distortion finer than the registration is claimed.
    """
    p = positions.reshape(-1, 2).astype(np.float64)
    s = shifts.reshape(-1, 2).astype(np.float64)
    wts = np.ones(len(p)) if weights is None else weights.reshape(-1).astype(np.float64)
    # positions not measured (NaN: a gap of an incomplete grid, an excluded PSF) are left out
    ok = np.isfinite(p).all(axis=1) & np.isfinite(s).all(axis=1) & np.isfinite(wts)
    wts = np.where(ok, np.clip(np.where(ok, wts, 0.0), 0, None), 0.0)
    design = np.column_stack([p, np.ones(len(p))])
    if np.linalg.matrix_rank(design[wts > 0]) < 3:
        raise InvalidInputError("the field positions do not span two directions; cannot fit "
                                "the shift map (need a 2-D grid)")
    sw = np.sqrt(wts)[ok, None]
    coef, *_ = np.linalg.lstsq(design[ok] * sw, s[ok] * sw, rcond=None)
    matrix, offset = coef[:2].T, coef[2]
    unitary, positive = linalg.polar(matrix)
    mirrored = bool(np.linalg.det(unitary) < 0)
    rotation = float(np.degrees(np.arctan2(unitary[1, 0], unitary[0, 0])))
    residuals = np.full_like(s, np.nan)
    residuals[ok] = s[ok] - design[ok] @ coef
    residuals = residuals.reshape(shifts.shape)
    used = wts > 0
    estimates, degree = _shift_map_estimates(p[used], s[used], wts[used], matrix, rotation,
                                             resolution_px)
    return ShiftMapFit(matrix=matrix, offset=offset, field_units=field_units,
                       rotation_deg=rotation, magnification_u=float(positive[0, 0]),
                       magnification_v=float(positive[1, 1]), shear=float(positive[0, 1]),
                       mirrored=mirrored, residuals=residuals, estimates=estimates,
                       distortion_degree=degree)


def _magnification_and_rotation(matrix: np.ndarray) -> np.ndarray:
    """``(sqrt(det P), rotation in degrees)`` of ``matrix = R · P`` (polar decomposition)."""
    unitary, positive = linalg.polar(matrix)
    det = positive[0, 0] * positive[1, 1] - positive[0, 1] ** 2
    return np.array([np.sqrt(max(det, 0.0)),
                     np.degrees(np.arctan2(unitary[1, 0], unitary[0, 0]))])


def _shift_map_estimates(p: np.ndarray, s: np.ndarray, w: np.ndarray, matrix: np.ndarray,
                         rotation: float, resolution_px: float = 0.0
                         ) -> tuple[dict[str, Estimate], int]:
    """:class:`ShiftMapFit.estimates` from the ``(n, 2)`` positions ``p``, shifts ``s`` and
    weights ``w`` the fit used, and the distortion test's polynomial degree (0: none)."""
    null_rotation = math.copysign(180.0, rotation) if abs(rotation) > 90.0 else 0.0
    design = np.column_stack([p, np.ones(len(p))])
    _, covariance, rss, dof = weighted_lstsq(design, s, w)
    if dof < 1:
        reason = "as many shift-map parameters as measurements: no residual to judge by"
        return {"magnification": undetermined(reason),
                "rotation_deg": undetermined(reason, null_rotation),
                "distortion_rms_px": undetermined(reason)}, 0
    # A[i, j] is coefficient j of output i: outputs independent, same covariance
    cov_a = np.kron(np.eye(2), covariance[:2, :2])
    base = _magnification_and_rotation(matrix)
    jacobian = np.empty((2, 4))
    step = 1e-6 * max(float(np.abs(matrix).max()), 1e-300)
    for k in range(4):
        delta = np.zeros(4)
        delta[k] = step
        up = _magnification_and_rotation(matrix + delta.reshape(2, 2))
        down = _magnification_and_rotation(matrix - delta.reshape(2, 2))
        diff = up - down
        diff[1] = (diff[1] + 180.0) % 360.0 - 180.0           # the angle's wrap at ±180°
        jacobian[:, k] = diff / (2 * step)
    sigma = np.sqrt(np.maximum(np.einsum("ik,kl,il->i", jacobian, cov_a, jacobian), 0.0))
    # a magnification different from 0 is the model against "shift = constant": the F-test
    # of the four linear coefficients
    _, _, rss_constant, _ = weighted_lstsq(design[:, 2:], s, w)
    p_map = f_test(rss_constant, rss, 4, dof)
    magnification = checked(base[0], sigma[0], 0.0, p_map)
    rotation_estimate = (checked(rotation, sigma[1], null_rotation, p_map)
                         if magnification.significant else
                         undetermined("the shift map is not significant", null_rotation))
    distortion, degree = _nonlinear_distortion(p, s, w, resolution_px)
    return {"magnification": magnification, "rotation_deg": rotation_estimate,
            "distortion_rms_px": distortion}, degree


def _sampling_terms(shifts: np.ndarray) -> np.ndarray:
    """``(n, 4)`` ``sin 2πφ``, ``cos 2πφ − 1`` per axis of the sub-pixel phase ``φ = s −
    round(s)``: pixel sampling biases a registration by a function of φ, which on a regular
    grid would pass for distortion."""
    phase = 2 * np.pi * (shifts - np.round(shifts))
    return np.column_stack([np.sin(phase), np.cos(phase) - 1.0])


def _monomials(p: np.ndarray, degree: int) -> np.ndarray:
    """``(n, T)`` monomials ``x^a y^b``, ``a + b <= degree``, of the positions scaled to
    ``[-1, 1]`` (the affine ones first)."""
    centred = p - p.mean(axis=0)
    x, y = (centred / max(float(np.abs(centred).max()), 1e-300)).T
    terms = [x, y, np.ones_like(x)]
    terms += [x ** (d - b) * y**b for d in range(2, degree + 1) for b in range(d + 1)]
    return np.column_stack(terms)


def _nonlinear_distortion(p: np.ndarray, s: np.ndarray, w: np.ndarray,
                          resolution_px: float = 0.0) -> tuple[Estimate, int]:
    """Debiased RMS of the shift map's non-linear part with its delta-method σ, and the F-test
    of the highest-degree polynomial (≤ :data:`DISTORTION_DEGREE`, as many residual dof as
    parameters) against the affine map; both with :func:`_sampling_terms`."""
    n = len(p)
    phase = _sampling_terms(s)
    for degree in range(DISTORTION_DEGREE, 1, -1):
        design = np.column_stack([_monomials(p, degree), phase])
        terms = design.shape[1]
        if n - terms >= terms and np.linalg.matrix_rank(design) == terms:
            break
    else:
        return undetermined(f"{n} positions are too few to test a polynomial shift map"), 0
    sw = np.sqrt(w)[:, None]
    q_full, _ = np.linalg.qr(design * sw)
    null_design = np.column_stack([design[:, :3], phase])
    q_affine, _ = np.linalg.qr(null_design * sw)
    extra = terms - null_design.shape[1]
    white = s * sw
    # the non-linear part at the positions: (projection on the polynomial − on the affine
    # map) of the whitened shifts, in px
    part = (q_full @ (q_full.T @ white) - q_affine @ (q_affine.T @ white)) / sw
    rss_full = float(np.sum((white - q_full @ (q_full.T @ white)) ** 2))
    rss_null = float(np.sum((white - q_affine @ (q_affine.T @ white)) ** 2))
    dof_full = 2 * (n - terms)
    noise = rss_full / dof_full                 # variance of a whitened shift component
    mean_square = float(np.mean(np.sum(part**2, axis=1)))
    # E|part|² = true² + noise · Σ_i M_ii / w_i (M the whitened projection difference)
    leverage = np.sum(q_full**2, axis=1) - np.sum(q_affine**2, axis=1)
    bias = 2.0 * noise * float(np.sum(leverage / w)) / n
    rms = math.sqrt(max(mean_square - bias, 0.0))
    plain = math.sqrt(mean_square)
    if plain > 0:
        # delta method on sqrt(mean |part|²): gradient wrt the whitened shifts
        gradient = (q_full @ (q_full.T @ (part / sw)) - q_affine @ (q_affine.T @ (part / sw)))
        sigma = math.sqrt(noise * float(np.sum(gradient**2))) / (n * plain)
    else:
        sigma = 0.0
    p_value = f_test(rss_null, rss_full, 2 * extra, dof_full)
    sigma = math.hypot(sigma, resolution_px / math.sqrt(12.0))
    if sigma <= 0:     # noise-free data: the F-test alone decides
        sigma = max(1e-12 * max(plain, 1e-300), 1e-300)
    return checked(rms, sigma, 0.0, p_value), degree
