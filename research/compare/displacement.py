"""Displacement maps: the local sub-pixel displacement of one image relative to another on
the caustic (dense optical flow, gain-matched, masked smoothing).

A displacement field ``D = (D_u, D_v)`` is ``(2, H, W)`` in pixels, ``u`` = column (right),
``v`` = row (down); ``other(x + D(x)) ≈ reference(x)`` (as in :mod:`psfkit.calibration.warp`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from psfkit.calibration.caustic import caustic_mask
from psfkit.calibration.preprocess import luminance
from psfkit.calibration.warp import dense_flow
from psfkit.errors import InvalidInputError
from research.compare.options import CompareOptions


@dataclass(frozen=True)
class DisplacementMap:
    """A displacement ``field`` ``(2, H, W)`` float32 ``(D_u, D_v)`` px (zero outside
    ``mask``) and the ``(H, W)`` bool ``mask`` where it is meaningful."""

    field: np.ndarray = dataclasses.field(repr=False)
    mask: np.ndarray = dataclasses.field(repr=False)

    def rms(self) -> float:
        """RMS length of the displacement over the mask (px; NaN on an empty mask)."""
        if not self.mask.any():
            return float("nan")
        return float(np.sqrt(np.mean(np.sum(self.field[:, self.mask] ** 2, axis=0))))


def masked_smooth(values: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of ``values`` ``(..., H, W)`` using only the pixels in ``mask``
    (normalised convolution); zero outside ``mask``."""
    m = mask.astype(np.float64)
    if sigma <= 0:
        return np.where(mask, values, 0).astype(np.float32)
    weight = ndimage.gaussian_filter(m, sigma, mode="constant")
    out = np.zeros(values.shape, np.float32)
    for index in np.ndindex(values.shape[:-2]):
        smooth = ndimage.gaussian_filter(values[index] * m, sigma, mode="constant")
        out[index] = np.where(mask, smooth / np.maximum(weight, 1e-12), 0)
    return out


def displacement_map(reference: np.ndarray, other: np.ndarray, mask: np.ndarray,
                     method: str = "dis", smooth_px: float = 3.0) -> DisplacementMap:
    """Local sub-pixel displacement of ``other`` relative to ``reference`` on ``mask``.

    ``reference``, ``other``: ``(H, W)`` non-negative images, gain-matched on the mask, then
    :func:`psfkit.calibration.warp.dense_flow` by ``method``, smoothed by a masked Gaussian of
    σ ``smooth_px``. Returns ``D`` with ``other(x + D(x)) ≈ reference(x)``, in px.
    """
    if reference.shape != other.shape or reference.ndim != 2 or mask.shape != reference.shape:
        raise InvalidInputError("displacement_map needs two 2-D images and a mask of one shape")
    if not mask.any():
        return DisplacementMap(np.zeros((2, *reference.shape), np.float32), mask)
    ref = np.clip(reference, 0, None).astype(np.float32)
    oth = np.clip(other, 0, None).astype(np.float32)
    # gain differences (vignetting) are not displacements: match the sums on the mask
    s_ref, s_oth = float(ref[mask].sum()), float(oth[mask].sum())
    if s_ref > 0 and s_oth > 0:
        oth = oth * np.float32(s_ref / s_oth)
    flow = dense_flow(ref, oth, method)
    return DisplacementMap(masked_smooth(flow, mask, smooth_px), mask)


def comparison_mask(base_luminance: np.ndarray, options: CompareOptions) -> np.ndarray:
    """Caustic mask of the measured ``Kbase`` luminance ``(H, W)`` (see
    :func:`psfkit.calibration.caustic.caustic_mask`)."""
    return caustic_mask(base_luminance, np.ones(base_luminance.shape, bool), options.mask_level,
                        options.mask_border, options.mask_dilate)


def caustic_support(kernels: np.ndarray, level: float = 0.02, dilate: int = 3) -> np.ndarray:
    """``(H, W)`` bool union of the caustic masks (:func:`~psfkit.calibration.caustic.caustic_mask`
    without a border) of ``kernels`` ``(K, C, H, W)`` or ``(K, H, W)`` (luminance)."""
    k = np.asarray(kernels, np.float32)
    if k.ndim == 4:
        k = np.stack([luminance(x) for x in k])
    if k.ndim != 3:
        raise InvalidInputError("caustic_support needs (K, C, H, W) or (K, H, W) kernels")
    valid = np.ones(k.shape[-2:], bool)
    out = np.zeros(k.shape[-2:], bool)
    for img in k:
        if float(np.abs(img).max()) > 0:
            out |= caustic_mask(np.clip(img, 0, None), valid, level, border=0, dilate=dilate)
    return out
