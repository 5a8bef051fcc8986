"""Mean absolute error of registered PSFs against the reference (paper, Sec. 4.1, Fig. 2).

With every PSF aligned to the reference by its measured shift (and, optionally, divided by its
gain), what remains is the error a shift-invariant model makes at that field position:
``MAE = mean_{c, x ∈ Ω} |p(x) − p0(x)|`` over the overlap ``Ω`` (saturated pixels excluded), in
the grid's stated normalization (the reference PSF has unit peak or unit sum).
"""

from __future__ import annotations

import numpy as np


def mean_absolute_error(reference: np.ndarray, aligned: np.ndarray, valid: np.ndarray,
                        gain: float = 1.0) -> float:
    """MAE of ``aligned / gain`` against ``reference`` over ``valid`` pixels, all channels.

    Parameters
    ----------
    reference, aligned : numpy.ndarray
        ``(C, H, W)`` in the same (normalized) units.
    valid : numpy.ndarray
        ``(H, W)`` bool.
    gain : float
        Divide ``aligned`` by this before comparing (1: no gain compensation).
    """
    if not valid.any():
        return float("nan")
    diff = np.abs(aligned / np.float32(gain) - reference).sum(axis=0)
    return float(np.sum(diff, where=valid, dtype=np.float64)
                 / (np.count_nonzero(valid) * reference.shape[0]))

