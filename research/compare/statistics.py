"""Agreement of two displacement maps or two kernels: Pearson correlation, end-point error,
slope, uncentred normalised correlation."""

from __future__ import annotations

import numpy as np

from psfkit.calibration.registration import normalized_cross_correlation
from research.compare.displacement import DisplacementMap


def pearson(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Pearson correlation of ``a`` and ``b`` (``(..., H, W)``) over ``mask`` (all leading
    components pooled); NaN when either is constant there or fewer than 3 values."""
    return normalized_cross_correlation(a, b, mask, float("nan"), 3)


def normalized_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Uncentred normalised correlation ``<a, b> / (|a| |b|)`` (cosine; NaN if either is 0)."""
    x = a.astype(np.float64).ravel()
    y = b.astype(np.float64).ravel()
    denom = float(np.linalg.norm(x) * np.linalg.norm(y))
    return float(np.dot(x, y) / denom) if denom > 0 else float("nan")


def map_agreement(a: DisplacementMap, b: DisplacementMap, min_displacement_px: float = 0.02
                  ) -> dict[str, float | int | str | None]:
    """How well displacement map ``a`` agrees with ``b`` on the intersection of their masks.

    Returns
    -------
    dict
        ``corr_u``, ``corr_v``, ``corr`` (Pearson, both components pooled; NaN when either map
        has no displacement), ``epe_px`` (mean end-point error), ``rms_a_px``, ``rms_b_px``,
        ``slope`` (least-squares ``a ≈ slope · b``), ``pixels`` and ``note`` (why the
        correlations are NaN, else None).
    """
    mask = a.mask & b.mask
    both = DisplacementMap(a.field, mask), DisplacementMap(b.field, mask)
    rms_a, rms_b = both[0].rms(), both[1].rms()
    out: dict[str, float | int | str | None] = {
        "pixels": int(mask.sum()), "rms_a_px": rms_a, "rms_b_px": rms_b,
        "epe_px": float(np.mean(np.hypot(*(a.field[:, mask] - b.field[:, mask]))))
        if mask.any() else float("nan"),
        "corr_u": float("nan"), "corr_v": float("nan"), "corr": float("nan"),
        "slope": float("nan"), "note": None}
    if not mask.any():
        out["note"] = "no common pixels"
        return out
    if not (rms_a >= min_displacement_px and rms_b >= min_displacement_px):
        out["note"] = (f"no displacement (RMS {rms_a:.3g} / {rms_b:.3g} px below "
                       f"{min_displacement_px} px): correlation undefined")
        return out
    out["corr_u"] = pearson(a.field[0], b.field[0], mask)
    out["corr_v"] = pearson(a.field[1], b.field[1], mask)
    out["corr"] = pearson(a.field, b.field, mask)
    fa, fb = a.field[:, mask].astype(np.float64), b.field[:, mask].astype(np.float64)
    out["slope"] = float(np.sum(fa * fb) / max(np.sum(fb * fb), 1e-300))
    return out
