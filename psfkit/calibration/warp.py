r"""Dense warp fields between registered PSFs, their affine part and their residual.

Convention: ``moving(x + d(x)) ≈ reference(x)``, ``d = (d_u, d_v)`` in pixels (``u`` = column,
``v`` = row). :func:`warp_field`: the affine part (magnification, anamorphic scale, shear,
rotation) by coarse-to-fine ECC (OpenCV ``findTransformECC``), reported about the image centre
(:class:`AffineWarp`); the residual by dense optical flow on the affine-compensated pair (DIS by
default: the most accurate and fastest in ``research/warp_methods.py``).

Tangential/sagittal anisotropy (:func:`transport_anisotropy`): a flow sees only motion normal
to a caustic line, which mixes ``t`` and ``s``. Instead, to first order an extra propagation
``(Δ_t, Δ_s)`` changes the intensity by
:math:`\delta I = -\Delta_t\,\partial_t(I a_t) - \Delta_s\,\partial_s(I a_s)` (``a`` the ray
angles), whose power at spatial-frequency angle φ from ``t`` goes as
:math:`(\Delta_t\cos^2\varphi + \Delta_s\sin^2\varphi)^2` for an isotropic diffuser; fitting
that angular profile (noise floor removed) gives :math:`\Delta_t/\Delta_s`, and
:func:`split_rms` splits the residual's RMS in that ratio.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.fft as sfft
from scipy import optimize

from psfkit.calibration.caustic import caustic_mask, erode
from psfkit.choices import FLOW_METHODS
from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.numerics.significance import Estimate, checked, f_test, undetermined
from psfkit.numerics.windows import tukey_window


@dataclass(frozen=True)
class AffineWarp:
    """Affine displacement ``d(x) = (M − I)(x − c) + t`` about the image centre ``c``.

    ``matrix`` is ``M`` acting on ``(u, v)``; ``translation`` is ``t`` (px).
    """

    matrix: np.ndarray
    translation: np.ndarray
    center: tuple[float, float]

    @property
    def scale_u(self) -> float:
        return float(self.matrix[0, 0])

    @property
    def scale_v(self) -> float:
        return float(self.matrix[1, 1])

    @property
    def shear(self) -> float:
        return float(0.5 * (self.matrix[0, 1] + self.matrix[1, 0]))

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(0.5 * (self.matrix[1, 0] - self.matrix[0, 1])))

    def directional_scale(self, azimuth_rad: float) -> tuple[float, float]:
        """Scale along the unit vector at ``azimuth_rad`` (tangential) and across it."""
        t = np.array([np.cos(azimuth_rad), np.sin(azimuth_rad)])
        s = np.array([-t[1], t[0]])
        return float(t @ self.matrix @ t), float(s @ self.matrix @ s)

    def displacement(self, shape: tuple[int, int]) -> np.ndarray:
        """``(2, H, W)`` field ``(d_u, d_v)`` on a grid of ``shape``."""
        v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
        du, dv = u - self.center[1], v - self.center[0]
        m = self.matrix - np.eye(2)
        return np.stack([m[0, 0] * du + m[0, 1] * dv + self.translation[0],
                         m[1, 0] * du + m[1, 1] * dv + self.translation[1]]).astype(np.float32)

    def to_dict(self, azimuth_rad: float | None = None) -> dict:
        out = {"scale_u": self.scale_u, "scale_v": self.scale_v, "shear": self.shear,
               "rotation_deg": self.rotation_deg, "translation_px": self.translation.tolist()}
        if azimuth_rad is not None:
            out["scale_tangential"], out["scale_sagittal"] = self.directional_scale(azimuth_rad)
        return out


@dataclass(frozen=True)
class WarpResult:
    """Dense warp between a reference PSF and another: ``residual`` ``(2, H, W)`` beyond the
    affine map, ``compensated`` the moving PSF without its affine part, ``mask`` where both are
    meaningful (inside both images, on or beside the caustic)."""

    affine: AffineWarp
    residual: np.ndarray
    compensated: np.ndarray
    mask: np.ndarray
    ecc: float

    def displacement(self) -> np.ndarray:
        """Total ``(2, H, W)`` displacement: ``moving(W(x + r)) ≈ reference(x)`` gives
        ``d = (W x − x) + M r``."""
        return self.affine.displacement(self.mask.shape) + np.einsum(
            "ij,jhw->ihw", self.affine.matrix, self.residual).astype(np.float32)


def _ecc_affine(reference: np.ndarray, moving: np.ndarray, mask: np.ndarray,
                levels: int, iterations: int, finest: int) -> tuple[np.ndarray, float]:
    """OpenCV ECC affine (2×3, maps reference pixel (u, v) to moving), coarse to fine, from
    level ``levels − 1`` down to level ``finest`` (level l is binned 2^l)."""
    warp = np.eye(2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-7)
    ecc = 0.0
    for level in range(levels - 1, finest - 1, -1):
        f = 2**level
        if min(reference.shape) // f < 32:
            continue
        ref_l = cv2.resize(reference, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        mov_l = cv2.resize(moving, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        mask_l = cv2.resize(mask.astype(np.uint8), (ref_l.shape[1], ref_l.shape[0]),
                            interpolation=cv2.INTER_NEAREST)
        # pixel centres: x = f·x_l + c with c = (f − 1)/2, so the level-l warp has the same
        # linear part and translation b_l = (b + (M − I)·c) / f
        centre = np.full(2, 0.5 * (f - 1))
        scaled = warp.copy()
        scaled[:, 2] = (warp[:, 2] + (warp[:, :2] - np.eye(2)) @ centre) / f
        try:
            ecc, scaled = cv2.findTransformECC(ref_l, mov_l, scaled, cv2.MOTION_AFFINE,
                                               criteria, mask_l, 3 if f > 1 else 1)
        except cv2.error as exc:
            reason = str(exc).strip().splitlines()[-1]
            raise InvalidInputError(f"affine registration did not converge ({reason})") from None
        warp = scaled.copy()
        warp[:, 2] = f * scaled[:, 2] - (scaled[:, :2] - np.eye(2)) @ centre
    return warp.astype(np.float64), float(ecc)


def affine_registration(reference: np.ndarray, moving: np.ndarray,
                        mask: np.ndarray | None = None, levels: int = 3,
                        iterations: int = 200, finest: int | None = None
                        ) -> tuple[AffineWarp, float]:
    """Affine map between two 2-D images by ECC maximisation: the :class:`AffineWarp` and the
    final correlation coefficient. ``finest``: the finest pyramid level (default: half
    resolution above 512 px a side, where the affine is as well determined, else full)."""
    ref = np.ascontiguousarray(reference, dtype=np.float32)
    mov = np.ascontiguousarray(moving, dtype=np.float32)
    mask = np.ones(ref.shape, bool) if mask is None else mask
    if finest is None:
        finest = 1 if min(ref.shape) > 512 else 0
    warp, ecc = _ecc_affine(ref, mov, mask, max(levels, finest + 1), iterations, finest)
    matrix = warp[:, :2]
    center = ((ref.shape[0] - 1) / 2.0, (ref.shape[1] - 1) / 2.0)
    c_uv = np.array([center[1], center[0]])
    translation = matrix @ c_uv + warp[:, 2] - c_uv
    return AffineWarp(matrix=matrix, translation=translation, center=center), ecc


def _to_uint8(image: np.ndarray, scale: float) -> np.ndarray:
    # square-root encoding spreads a caustic's dynamic range over the 8 bits OpenCV flows take
    return np.clip(np.sqrt(np.clip(image, 0, None) / scale) * 255.0, 0, 255).astype(np.uint8)


def dense_flow(reference: np.ndarray, moving: np.ndarray, method: str = "dis") -> np.ndarray:
    """Dense flow ``(2, H, W)`` = ``(d_u, d_v)`` with ``moving(x + d(x)) ≈ reference(x)``:
    ``method`` OpenCV DIS or Farneback (on square-root-encoded 8-bit images) or scikit-image's
    ILK or TV-L1 (on float images)."""
    if method not in FLOW_METHODS:
        raise ConfigurationError(f"unknown flow method {method!r} (use {', '.join(FLOW_METHODS)})")
    if method in ("dis", "farneback"):
        scale = max(float(reference.max()), float(moving.max()), 1e-30)
        a, b = _to_uint8(reference, scale), _to_uint8(moving, scale)
        if method == "dis":
            dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
            dis.setPatchSize(12)
            dis.setPatchStride(4)
            flow = dis.calc(a, b, None)
        else:
            flow = cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 21, 5, 7, 1.5, 0)
        return np.moveaxis(flow, -1, 0).astype(np.float32)
    from skimage.registration import optical_flow_ilk, optical_flow_tvl1

    scale = max(float(reference.max()), 1e-30)
    fn = optical_flow_ilk if method == "ilk" else optical_flow_tvl1
    v, u = fn(reference / scale, moving / scale)
    return np.stack([u, v]).astype(np.float32)


def bounding_box(mask: np.ndarray, margin: int) -> tuple[slice, slice]:
    """``(rows, cols)`` slices around ``mask``'s nonzero pixels, ``margin`` px wider on each
    side, clipped to the image."""
    rows, cols = np.nonzero(mask)
    return (slice(max(rows.min() - margin, 0), min(rows.max() + margin + 1, mask.shape[0])),
            slice(max(cols.min() - margin, 0), min(cols.max() + margin + 1, mask.shape[1])))


def warp_field(reference: np.ndarray, moving: np.ndarray, valid: np.ndarray | None = None,
               method: str = "dis") -> WarpResult:
    """Dense warp from ``reference`` to a registered, gain-compensated ``moving`` PSF (both
    ``(H, W)``; ``valid``: where both have data; ``method``: see :func:`dense_flow`).

    Computed on the caustic's bounding box; the affine map is reported about the full image's
    centre and the arrays are full size (zero outside the box).
    """
    if reference.shape != moving.shape or reference.ndim != 2:
        raise InvalidInputError("warp_field needs two 2-D images of one shape")
    h, w = reference.shape
    valid = np.ones((h, w), bool) if valid is None else valid
    mask = caustic_mask(reference, valid)
    if mask.sum() < 64:
        raise InvalidInputError("too little of the PSF overlaps the reference for a warp field")
    box = bounding_box(mask, margin=16)
    ref = np.where(valid, reference, 0).astype(np.float32)[box]
    mov = np.where(valid, moving, 0).astype(np.float32)[box]
    local, ecc = affine_registration(ref, mov, erode(valid[box], 4))
    origin = np.array([box[1].start, box[0].start], dtype=np.float64)   # (u0, v0)
    # the same affine map written about the full image's centre
    center = ((h - 1) / 2.0, (w - 1) / 2.0)
    c_local = np.array([local.center[1], local.center[0]])
    c_full = np.array([center[1], center[0]])
    translation = local.translation + (local.matrix - np.eye(2)) @ (c_full - origin - c_local)
    affine = AffineWarp(matrix=local.matrix, translation=translation, center=center)
    warp = np.hstack([local.matrix, (local.translation + c_local - local.matrix @ c_local
                                     )[:, None]]).astype(np.float32)
    compensated_box = cv2.warpAffine(mov, warp, (mov.shape[1], mov.shape[0]),
                                     flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    residual = np.zeros((2, h, w), np.float32)
    residual[(slice(None), *box)] = dense_flow(ref, compensated_box, method)
    compensated = np.zeros((h, w), np.float32)
    compensated[box] = compensated_box
    return WarpResult(affine=affine, residual=residual, compensated=compensated, mask=mask,
                      ecc=ecc)


def transport_anisotropy(reference: np.ndarray, compensated: np.ndarray, mask: np.ndarray,
                         azimuth_rad: float, band: tuple[float, float] = (0.02, 0.2),
                         noise_band: tuple[float, float] = (0.42, 0.5), n_angles: int = 36
                         ) -> float:
    """Ratio ``Δ_t/Δ_s`` of the tangential to the sagittal transport between two PSFs.

    Parameters
    ----------
    reference, compensated : numpy.ndarray
        ``(H, W)``: the reference and the other PSF without its shift, gain and affine part.
    mask : numpy.ndarray
        ``(H, W)`` bool; its bounding box is analysed.
    azimuth_rad : float
        Direction of ``t`` from ``+u`` towards ``+v``.
    band, noise_band : (float, float)
        Frequencies (cycles/px) of the fitted angular profile, and of the white noise floor.

    Returns
    -------
    float
        NaN for a region too small, without signal, or without sagittal transport above noise.
    """
    if not mask.any():
        return float("nan")
    box = bounding_box(mask, margin=0)
    ref, mov = reference[box].astype(np.float64), compensated[box].astype(np.float64)
    if min(ref.shape) < 32:
        return float("nan")
    mov = mov * (ref.sum() / max(mov.sum(), 1e-30))
    window = tukey_window(ref.shape[0], 0.3)[:, None] * tukey_window(ref.shape[1], 0.3)[None]
    # real input: the half spectrum holds every angle in [0, π) once
    power = np.abs(sfft.rfft2((mov - ref) * window, workers=-1)) ** 2
    gv = np.fft.fftfreq(ref.shape[0])[:, None]
    gu = np.fft.rfftfreq(ref.shape[1])[None]
    radius = np.hypot(gu, gv)
    phi = np.mod(np.arctan2(gv, gu) - azimuth_rad, np.pi)
    floor = float(np.median(power[(radius > noise_band[0]) & (radius < noise_band[1])]))
    inside = (radius > band[0]) & (radius < band[1])
    index = np.minimum((phi[inside] / np.pi * n_angles).astype(int), n_angles - 1)
    counts = np.bincount(index, minlength=n_angles)
    profile = np.bincount(index, weights=power[inside], minlength=n_angles) \
        / np.maximum(counts, 1) - floor
    centres = (np.arange(n_angles) + 0.5) / n_angles * np.pi
    c2, s2 = np.cos(centres) ** 2, np.sin(centres) ** 2
    design = np.column_stack([c2**2, s2**2, 2 * c2 * s2])
    coef, _ = optimize.nnls(design[counts > 0], profile[counts > 0])
    if coef[1] <= 0:
        # no sagittal transport above the noise: the ratio is not determined (NaN, not +inf,
        # which no report could draw as an axis limit or print as a number)
        return float("nan")
    return float(np.sqrt(coef[0] / coef[1]))


def split_rms(total_rms: float, anisotropy: float) -> tuple[float, float]:
    """Split an RMS displacement into tangential and sagittal parts with ratio ``anisotropy``
    (``total² = t² + s²``, ``t/s = anisotropy``)."""
    if not np.isfinite(total_rms) or not np.isfinite(anisotropy):
        return float("nan"), float("nan")
    sagittal = total_rms / np.sqrt(1.0 + anisotropy**2)
    return float(anisotropy * sagittal), float(sagittal)


#: Bounds of the growth exponent in :func:`fit_growth` (astigmatism predicts 2).
GROWTH_EXPONENT_BOUNDS = (0.1, 8.0)


@dataclass(frozen=True)
class GrowthFit:
    """``rms(θ)² = floor² + (scale_10deg · (θ/10°)^exponent)²`` fitted over the grid.

    ``growth``: ``scale_10deg`` as an :class:`~psfkit.numerics.significance.Estimate` (null 0,
    F-test against a constant); ``exponent_estimate``: determined only for a significant growth.
    """

    floor: float
    scale_10deg: float
    exponent: float
    exponent_std: float
    floor_std: float = math.nan
    growth: Estimate = field(default_factory=lambda: undetermined("not fitted"))
    exponent_estimate: Estimate = field(default_factory=lambda: undetermined("not fitted"))

    @property
    def significant(self) -> bool:
        return self.growth.significant

    def to_dict(self) -> dict:
        return {"floor": self.floor, "floor_std": self.floor_std,
                "scale_10deg": self.scale_10deg, "scale_10deg_std": self.growth.sigma,
                "exponent": self.exponent, "exponent_std": self.exponent_std,
                "estimates": {"scale_10deg": self.growth.to_dict(),
                              "exponent": self.exponent_estimate.to_dict()}}


def _growth_model(t: np.ndarray, floor: float, scale: float, exponent: float) -> np.ndarray:
    return np.sqrt(floor**2 + (scale * (t / 10.0) ** exponent) ** 2)


#: A growth whose 1σ exceeds this many times the largest residual measured is not determined.
UNCONSTRAINED = 100.0


def fit_growth(theta_deg: np.ndarray, rms: np.ndarray, weights: np.ndarray | None = None
               ) -> GrowthFit | None:
    """Fit how a residual RMS grows with field angle above the flow's error floor
    (:class:`GrowthFit`; astigmatism predicts exponent 2). ``None`` with fewer than four finite
    points or no convergence; σ from the residual-scaled covariance."""
    theta, values = np.ravel(theta_deg), np.ravel(rms)
    w = np.ones_like(values) if weights is None else np.ravel(weights)
    ok = np.isfinite(theta) & np.isfinite(values) & (theta > 0) & (w > 0)
    if ok.sum() < 4:
        return None
    theta, values, w = theta[ok], values[ok], w[ok]
    low, high = GROWTH_EXPONENT_BOUNDS
    start = [float(np.min(values)), max(float(np.max(values)), 1e-12), 2.0]
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            # a flat profile leaves the covariance undetermined: that is a result (below)
            warnings.simplefilter("ignore", optimize.OptimizeWarning)
            popt, pcov = optimize.curve_fit(_growth_model, theta, values, p0=start,
                                            sigma=1.0 / np.sqrt(w), maxfev=20000,
                                            bounds=([0.0, 0.0, low], [np.inf, np.inf, high]))
    except (RuntimeError, ValueError):
        return None
    sigma = np.sqrt(np.abs(np.diag(pcov)))
    with np.errstate(all="ignore"):
        rss = float(np.sum(w * (values - _growth_model(theta, *popt)) ** 2))
    flat = float(np.sum(w * values) / np.sum(w))
    p_value = f_test(float(np.sum(w * (values - flat) ** 2)), rss, 2, len(values) - 3)
    growth = checked(popt[1], sigma[1], 0.0, p_value)
    if growth.determined and growth.sigma > UNCONSTRAINED * float(np.max(values)):
        # an extrapolation the positions do not constrain (a compact PSF's field of a degree:
        # "2.25e+08 ± 6.63e+09 px at 10 deg" from residuals of 0.1 px)
        growth = undetermined(f"the positions (θ ≤ {float(np.max(theta)):.2g}°) do not "
                              "constrain it at 10°")
    if not growth.significant:
        exponent = undetermined("the residual does not grow significantly above its floor")
    elif min(popt[2] - low, high - popt[2]) < 1e-3 * (high - low):
        exponent = undetermined(f"the fit ran to the bound {popt[2]:.3g} of the exponent")
    else:
        exponent = checked(popt[2], sigma[2], 0.0, p_value)
    return GrowthFit(floor=float(popt[0]), scale_10deg=float(popt[1]), exponent=float(popt[2]),
                     exponent_std=float(sigma[2]), floor_std=float(sigma[0]), growth=growth,
                     exponent_estimate=exponent)


def geometric_anisotropy(theta_deg: np.ndarray) -> np.ndarray:
    """Geometric-optics ratio ``(1/cos³θ − 1) / (1/cosθ − 1)`` of tangential to sagittal
    extra propagation distance (→ 3 on axis)."""
    c = np.cos(np.deg2rad(np.asarray(theta_deg, dtype=np.float64)))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(c < 1.0, (1 / c**3 - 1) / (1 / c - 1), 3.0)
