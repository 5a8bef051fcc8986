"""Where a PSF is on its frame: the bounding box of its support, and windows cut around it.

Figures show the PSF, not the frame: a lens camera's PSF of a few pixels on a 4000-px sensor
is invisible in a picture of the whole frame, and a caustic leaves dark borders. The box is
found once on the reference PSF and moved by each position's registered shift, so every
window shows the same part of the PSF.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: support: above this fraction of the (denoised) peak ...
SUPPORT_LEVEL = 0.02
#: ... and above this many noise standard deviations of the denoised image
SUPPORT_NOISE_SIGMAS = 5.0


def support_box(image: np.ndarray, level: float = SUPPORT_LEVEL, margin: float = 0.15,
                min_margin: int = 3) -> tuple[slice, slice]:
    """Bounding box of the support of a PSF, with a margin.

    The image is denoised (a 3 × 3 median removes hot pixels, a Gaussian of σ = 1 px averages
    the read noise) and thresholded at the larger of ``level`` × its peak and
    :data:`SUPPORT_NOISE_SIGMAS` robust noise deviations (MAD over the frame: a compact PSF
    leaves the frame mostly background); the box of the pixels above it grows by
    ``margin`` × its size on each side (at least ``min_margin`` px), clipped to the frame.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` PSF (luminance), dark level removed.
    level : float
        Threshold as a fraction of the denoised peak.
    margin : float
        Margin on each side as a fraction of the support's extent along that axis.
    min_margin : int
        Smallest margin, px.

    Returns
    -------
    tuple of slice
        ``(rows, cols)``; the whole frame when nothing rises above the threshold.
    """
    image = np.nan_to_num(np.asarray(image, dtype=np.float32))
    smooth = ndimage.gaussian_filter(ndimage.median_filter(image, size=3), 1.0)
    peak = float(smooth.max())
    if peak <= 0:
        return slice(0, image.shape[0]), slice(0, image.shape[1])
    median = float(np.median(smooth))
    noise = 1.4826 * float(np.median(np.abs(smooth - median)))
    threshold = max(level * peak, median + SUPPORT_NOISE_SIGMAS * noise)
    rows, cols = np.nonzero(smooth > threshold)
    if rows.size == 0:
        return slice(0, image.shape[0]), slice(0, image.shape[1])
    out = []
    for lo, hi, size in ((rows.min(), rows.max(), image.shape[0]),
                         (cols.min(), cols.max(), image.shape[1])):
        pad = max(min_margin, int(np.ceil(margin * (hi - lo + 1))))
        out.append(slice(max(int(lo) - pad, 0), min(int(hi) + pad + 1, size)))
    return out[0], out[1]


def crop_window(image: np.ndarray, box: tuple[slice, slice], offset: tuple[int, int] = (0, 0),
                fill: float = np.nan) -> np.ndarray:
    """The window ``box`` of ``image`` moved by ``offset`` px, ``fill`` outside the frame.

    Parameters
    ----------
    image : numpy.ndarray
        ``(..., H, W)``.
    box : tuple of slice
        ``(rows, cols)`` with explicit starts and stops (:func:`support_box`).
    offset : (int, int)
        ``(dv, du)``: rows, columns to move the window by (a PSF displaced by the registered
        shift ``(du, dv)`` stays in view).
    fill : float
        Value of the window's pixels outside the frame (NaN: drawn as "off the sensor").

    Returns
    -------
    numpy.ndarray
        ``(..., h, w)`` float32, the size of ``box``.
    """
    *lead, height, width = image.shape
    r0, c0 = box[0].start + int(offset[0]), box[1].start + int(offset[1])
    h, w = box[0].stop - box[0].start, box[1].stop - box[1].start
    out = np.full((*lead, h, w), fill, dtype=np.float32)
    rs, re = max(r0, 0), min(r0 + h, height)
    cs, ce = max(c0, 0), min(c0 + w, width)
    if rs < re and cs < ce:
        out[..., rs - r0:re - r0, cs - c0:ce - c0] = image[..., rs:re, cs:ce]
    return out
