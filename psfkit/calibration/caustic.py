"""The caustic (thin bright lines) of a PSF or kernel as a mask: where displacements and
kernel changes are meaningful."""

from __future__ import annotations

import cv2
import numpy as np


def caustic_mask(reference: np.ndarray, valid: np.ndarray, level: float = 0.02,
                 border: int = 8, dilate: int = 3) -> np.ndarray:
    """Pixels where a displacement is meaningful: on or beside the caustic (within ``dilate``
    px of a pixel above ``level`` of the peak, so that the flanks of thin caustic lines, where
    the gradients are, are kept), inside ``valid`` and ``border`` px away from its edge."""
    inner = erode(valid, border)
    if not inner.any():
        return inner
    bright = (reference > level * float(reference[inner].max())).astype(np.uint8)
    near = cv2.dilate(bright, np.ones((2 * dilate + 1, 2 * dilate + 1), np.uint8)) > 0
    return inner & near


def erode(mask: np.ndarray, pixels: int) -> np.ndarray:
    """Erode a bool mask by a square of half-size ``pixels`` (outside counts as False)."""
    if pixels <= 0:
        return mask
    padded = np.pad(mask.astype(np.uint8), 1)
    kernel = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return cv2.erode(padded, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)[
        1:-1, 1:-1] > 0
