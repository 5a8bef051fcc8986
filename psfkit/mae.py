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


def radial_profile(values: np.ndarray, radius: np.ndarray, n_bins: int = 6
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and standard deviation of ``values`` in equal-width bins of ``radius``.

    Returns ``(bin_centres, mean, std)``; empty bins are dropped.
    """
    v, r = values.reshape(-1), radius.reshape(-1)
    ok = np.isfinite(v) & np.isfinite(r)
    v, r = v[ok], r[ok]
    edges = np.linspace(0.0, r.max() * (1 + 1e-9), n_bins + 1) if r.size else np.zeros(2)
    idx = np.clip(np.digitize(r, edges) - 1, 0, n_bins - 1)
    centres, means, stds = [], [], []
    for b in range(n_bins):
        sel = idx == b
        if sel.any():
            centres.append(r[sel].mean())
            means.append(v[sel].mean())
            stds.append(v[sel].std())
    return np.array(centres), np.array(means), np.array(stds)
