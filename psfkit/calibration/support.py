"""Where a PSF is on its frame: the bounding box of its support, and windows cut around it
(figures show the PSF, not the frame; the reference's box moved by each registered shift)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from psfkit.numerics.resample import bin_image, binning_factor

#: support: above this fraction of the (denoised) peak ...
SUPPORT_LEVEL = 0.02
#: ... and above this many noise standard deviations of the denoised image
SUPPORT_NOISE_SIGMAS = 5.0
#: the support is found on a copy binned to at most this many pixels a side (fast on 12-Mpx
#: frames; the margin covers the binning)
SUPPORT_WORKING_PX = 1024


def support_box(image: np.ndarray, level: float = SUPPORT_LEVEL, margin: float = 0.15,
                min_margin: int = 3) -> tuple[slice, slice]:
    """``(rows, cols)`` bounding box of the support of an ``(H, W)`` PSF, with a margin.

    The image, denoised (3 × 3 median, Gaussian σ = 1 px), is thresholded at the larger of
    ``level`` × its peak and :data:`SUPPORT_NOISE_SIGMAS` robust noise deviations; the
    connected pieces that are bright (¼ of the peak) or large (1/20 of the largest) are the
    PSF. Their box grows by ``margin`` × its extent a side (at least ``min_margin`` px),
    clipped to the frame; the whole frame when nothing rises above the threshold.
    """
    image = np.nan_to_num(np.asarray(image, dtype=np.float32))
    height, width = image.shape
    whole = slice(0, height), slice(0, width)
    factor = binning_factor(image.shape, SUPPORT_WORKING_PX)
    work = bin_image(image, factor) / np.float32(factor**2)
    smooth = ndimage.gaussian_filter(ndimage.median_filter(work, size=3), 1.0)
    peak = float(smooth.max())
    if peak <= 0:
        return whole
    median = float(np.median(smooth))
    noise = 1.4826 * float(np.median(np.abs(smooth - median)))
    threshold = max(level * peak, median + SUPPORT_NOISE_SIGMAS * noise)
    above = smooth > threshold
    labels, count = ndimage.label(above, structure=np.ones((3, 3)))
    if count == 0:
        return whole
    # the PSF's pieces, not noise that crossed the threshold: a piece is kept when it is
    # bright (a quarter of the peak) or large (a twentieth of the largest piece)
    index = np.arange(1, count + 1)
    sizes = ndimage.sum_labels(above, labels, index)
    peaks = ndimage.maximum(smooth, labels, index)
    keep = index[(peaks >= 0.25 * peak) | (sizes >= 0.05 * sizes.max())]
    rows, cols = np.nonzero(np.isin(labels, keep))
    out = []
    for lo, hi, size in ((rows.min(), rows.max(), height), (cols.min(), cols.max(), width)):
        lo, hi = int(lo) * factor, (int(hi) + 1) * factor       # full-resolution pixels
        pad = max(min_margin, factor, int(np.ceil(margin * (hi - lo))))
        out.append(slice(max(lo - pad, 0), min(hi + pad, size)))
    return out[0], out[1]


def crop_window(image: np.ndarray, box: tuple[slice, slice], offset: tuple[int, int] = (0, 0),
                fill: float = np.nan) -> np.ndarray:
    """The window ``box`` (explicit ``(rows, cols)`` slices) of ``image`` ``(..., H, W)``
    moved by ``offset`` ``(dv, du)`` px, ``fill`` outside the frame (NaN: "off the sensor");
    ``(..., h, w)`` float32."""
    *lead, height, width = image.shape
    r0, c0 = box[0].start + int(offset[0]), box[1].start + int(offset[1])
    h, w = box[0].stop - box[0].start, box[1].stop - box[1].start
    out = np.full((*lead, h, w), fill, dtype=np.float32)
    rs, re = max(r0, 0), min(r0 + h, height)
    cs, ce = max(c0, 0), min(c0 + w, width)
    if rs < re and cs < ce:
        out[..., rs - r0:re - r0, cs - c0:ce - c0] = image[..., rs:re, cs:ce]
    return out
