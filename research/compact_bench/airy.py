"""The compact bench's PSF: a pixel-integrated Airy pattern ``I(r) ∝ (2 J₁(kr)/kr)²`` of a given
FWHM, optionally stretched along one axis, on a square stamp.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special

#: Sub-samples per pixel side (pixel integration).
OVERSAMPLE = 5
#: ``x`` at which the Airy intensity ``(2 J₁(x)/x)²`` is half its peak.
AIRY_HALF_MAX_X = 1.616339948310703


def airy_stamp(size: int, centre: tuple[float, float], fwhm_px: float, axis_ratio: float = 1.0,
               orientation_rad: float = 0.0) -> np.ndarray:
    """A pixel-integrated Airy PSF on a ``size × size`` stamp, unit sum.

    Parameters
    ----------
    size : int
        Stamp side, px.
    centre : (float, float)
        ``(x, y)`` of the PSF centre (pixel centres at integers).
    fwhm_px : float
        FWHM along the minor axis, px.
    axis_ratio : float
        Major / minor FWHM (≥ 1).
    orientation_rad : float
        Major axis direction, radians from ``+x`` towards ``+y``.

    Returns
    -------
    numpy.ndarray
        ``(size, size)`` float64, sums to 1.
    """
    offsets = (np.arange(OVERSAMPLE) + 0.5) / OVERSAMPLE - 0.5
    grid = (np.arange(size)[:, None] + offsets[None, :]).ravel()       # sub-sample centres
    dx = grid[None, :] - centre[0]
    dy = grid[:, None] - centre[1]
    cos, sin = math.cos(orientation_rad), math.sin(orientation_rad)
    along = (dx * cos + dy * sin) / axis_ratio
    across = -dx * sin + dy * cos
    x = np.hypot(along, across) * (2.0 * AIRY_HALF_MAX_X / fwhm_px)
    small = x < 1e-8
    x = np.where(small, 1.0, x)
    intensity = np.where(small, 1.0, (2.0 * special.j1(x) / x) ** 2)
    pixels = intensity.reshape(size, OVERSAMPLE, size, OVERSAMPLE).sum(axis=(1, 3))
    return pixels / pixels.sum()
