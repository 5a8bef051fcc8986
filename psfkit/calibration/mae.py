"""Energy-normalised mean absolute error of registered PSFs against the reference (paper,
Sec. 4.1, Fig. 2): ``MAE = Σ_{c, x ∈ S ∩ Ω} |p − p0| / Σ_{c, x ∈ S ∩ Ω} p0``, ``Ω`` the
registered overlap (saturated pixels excluded), ``S`` either PSF's support: the fraction of the
centre PSF's light a shift-invariant model misplaces (0: same PSF; 2: nothing in common),
independent of the frame's size and of the grid's normalization.
"""

from __future__ import annotations

import numpy as np


def mean_absolute_error(reference: np.ndarray, aligned: np.ndarray, valid: np.ndarray,
                        gain: float = 1.0) -> float:
    """Energy-normalised MAE of ``aligned / gain`` against ``reference`` (both ``(C, H, W)``)
    over the ``(H, W)`` bool ``valid`` (:attr:`~psfkit.calibration.alignment.AlignedPsf.compared`);
    NaN when ``valid`` is empty or holds no light of the reference."""
    if not valid.any():
        return float("nan")
    diff = np.abs(aligned / np.float32(gain) - reference).sum(axis=0)
    light = float(np.sum(reference.sum(axis=0), where=valid, dtype=np.float64))
    if light <= 0:
        return float("nan")
    return float(np.sum(diff, where=valid, dtype=np.float64)) / light
