"""Mean absolute error of registered PSFs against the reference (paper, Sec. 4.1, Fig. 2).

With every PSF aligned to the reference by its measured shift (and, optionally, divided by its
gain), what remains is the error a shift-invariant model makes at that field position. The
MAE is **energy-normalised over the PSF's support**:

``MAE = Σ_{c, x ∈ S ∩ Ω} |p(x) − p0(x)| / Σ_{c, x ∈ S ∩ Ω} p0(x)``,

``Ω`` the registered overlap (saturated pixels excluded), ``S`` the support of either PSF
(:func:`psfkit.calibration.alignment.psf_support`): the mean absolute error divided by the
reference's mean over the same pixels, i.e. the fraction of the centre PSF's light that a
shift-invariant model puts in the wrong place (0: the same PSF; 2: no light in common). It does
not depend on the frame's size (a star gives the same MAE on a 1024² frame and on a 63² cut-out; a
mean over the overlap falls with the frame's area and rises with the field as the overlap
shrinks), nor on the grid's normalization (``max`` or ``sum``), and compares compact PSFs with
caustics.
"""

from __future__ import annotations

import numpy as np


def mean_absolute_error(reference: np.ndarray, aligned: np.ndarray, valid: np.ndarray,
                        gain: float = 1.0) -> float:
    """Energy-normalised MAE of ``aligned / gain`` against ``reference`` over ``valid``.

    Parameters
    ----------
    reference, aligned : numpy.ndarray
        ``(C, H, W)`` in the same (normalized) units.
    valid : numpy.ndarray
        ``(H, W)`` bool: the pixels compared, the PSFs' support inside the registered
        overlap (:attr:`psfkit.calibration.alignment.AlignedPsf.compared`).
    gain : float
        Divide ``aligned`` by this before comparing (1: no gain compensation).

    Returns
    -------
    float
        ``Σ |aligned/gain − reference| / Σ reference`` over ``valid`` and all channels; NaN
        when ``valid`` is empty or holds no light of the reference.
    """
    if not valid.any():
        return float("nan")
    diff = np.abs(aligned / np.float32(gain) - reference).sum(axis=0)
    light = float(np.sum(reference.sum(axis=0), where=valid, dtype=np.float64))
    if light <= 0:
        return float("nan")
    return float(np.sum(diff, where=valid, dtype=np.float64)) / light
