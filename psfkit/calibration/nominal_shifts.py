"""Where a shift-invariant forward model puts each PSF of a grid (:func:`nominal_shifts`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from psfkit.calibration.alignment import RELIABLE_OVERLAP
from psfkit.calibration.shift_map import ShiftMapFit, fit_shift_map
from psfkit.errors import InvalidInputError
from psfkit.io.grid import GridPosition

#: Least share of the registered shifts' spread (weighted variance) the affine map must explain
#: to place the PSFs (:func:`nominal_shifts`): a scan of pre-centred cut-outs has shifts of
#: centring residuals, which no field map predicts.
MIN_EXPLAINED = 0.9
#: How :func:`nominal_shifts` placed the PSFs (``NominalShifts.source``).
SHIFT_SOURCES = {
    "affine": "the affine field-to-shift map of the positions with at least "
              f"{100 * RELIABLE_OVERLAP:.0f}% of the centre PSF's light in their registered "
              "overlap (reliable positions)",
    "affine (all positions)": "the affine field-to-shift map of every position, weighted by "
                              "the centre PSF's light in its overlap (the reliable ones do not "
                              "span two directions)",
    "registered": "each PSF's own registered shift (no two-dimensional field to fit a map to)",
    "registered (no map)": "each PSF's own registered shift: the affine field-to-shift map "
                           f"explains less than {100 * MIN_EXPLAINED:.0f}% of their spread "
                           "(cut-outs around each PSF, or a field too small to move it)",
}


@dataclass(frozen=True)
class NominalShifts:
    """Where the forward model puts each PSF: ``shifts`` ``(row, col)`` → ``(du, dv)`` px
    (``(0, 0)`` at the centre), ``source`` a key of :data:`SHIFT_SOURCES`, ``fit`` the affine
    map (or ``None``), ``deviation_px`` the largest ``|registered − nominal|`` (left in the
    kernels), ``positions_used`` how many positions determined the map."""

    shifts: dict[tuple[int, int], tuple[float, float]]
    source: str
    fit: ShiftMapFit | None
    positions_used: int
    deviation_px: float

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "meaning": SHIFT_SOURCES[self.source],
                "positions_used": self.positions_used,
                "max_deviation_from_registered_px": self.deviation_px,
                "map": self.fit.to_dict() if self.fit is not None else None}


def _explained(fit: ShiftMapFit, registered: np.ndarray, weights: np.ndarray) -> float:
    """``1 − Σ w |residual|² / Σ w |shift − mean|²`` (1 when the shifts do not spread)."""
    residuals = fit.residuals.reshape(-1, 2)
    ok = np.isfinite(residuals).all(axis=1) & (weights > 0)
    if not ok.any():
        return 1.0
    w = weights[ok]
    spread = registered[ok] - np.average(registered[ok], axis=0, weights=w)
    total = float(np.sum(w[:, None] * spread**2))
    return 1.0 - float(np.sum(w[:, None] * residuals[ok] ** 2)) / total if total > 0 else 1.0


def field_units(positions: list[GridPosition]) -> str:
    """The unit of the positions' field coordinates: monitor px, tan of the field angles, or
    grid steps."""
    if all(p.monitor_px is not None for p in positions):
        return "monitor px"
    if all(p.field_deg is not None for p in positions):
        return "tan(field angle)"
    return "grid steps"


def _field_coordinates(positions: list[GridPosition], center: GridPosition
                       ) -> tuple[np.ndarray, str]:
    """``(P, 2)`` field coordinates (grid steps from ``center`` without any) and their unit."""
    units = field_units(positions)
    if units == "monitor px":
        return np.array([p.monitor_px for p in positions], dtype=np.float64), units
    if units == "tan(field angle)":
        return (np.tan(np.deg2rad(np.array([p.field_deg for p in positions], dtype=np.float64))),
                units)
    return (np.array([(p.col - center.col, p.row - center.row) for p in positions],
                     dtype=np.float64), units)


def nominal_shifts(positions: list[GridPosition], registered: np.ndarray, overlap: np.ndarray,
                   center: tuple[int, int]) -> NominalShifts:
    """The shifts at which a shift-invariant forward model sees each PSF.

    The forward model places a PSF linearly in its field position (``docs/forward-models.md``);
    what a PSF does beyond that is for the eigen-kernels to describe, and the registration of a
    PSF mostly off the sensor is biased by its deformation. So an affine map
    (:func:`~psfkit.calibration.shift_map.fit_shift_map`, weighted by overlap) is fitted to the
    positions with at least :data:`~psfkit.calibration.alignment.RELIABLE_OVERLAP` of the centre
    PSF's light in their overlap and re-based to ``(0, 0)`` at the centre. Fallbacks: every
    position (the reliable ones do not span two directions), then the registered shifts (one
    row, or a map explaining less than :data:`MIN_EXPLAINED` of their spread).

    Parameters
    ----------
    positions : list of GridPosition
        The accepted positions, centre included.
    registered : numpy.ndarray
        ``(P, 2)`` registered shifts ``(du, dv)`` px.
    overlap : numpy.ndarray
        ``(P,)`` their :attr:`~psfkit.calibration.alignment.AlignedPsf.support_overlap`.
    center : (int, int)
        Grid index of the centre PSF.
    """
    registered = np.asarray(registered, dtype=np.float64).reshape(-1, 2)
    overlap = np.asarray(overlap, dtype=np.float64).reshape(-1)
    if not len(positions) == len(registered) == len(overlap):
        raise ValueError("positions, registered and overlap must have one entry per position")
    at_center = [i for i, p in enumerate(positions) if (p.row, p.col) == center]
    if not at_center:
        raise ValueError("the centre PSF must be among the positions")
    coords, units = _field_coordinates(positions, positions[at_center[0]])
    fit, source, used = None, "registered", len(positions)
    for name, weights in (("affine", np.where(overlap >= RELIABLE_OVERLAP, overlap, 0.0)),
                          ("affine (all positions)", overlap)):
        try:
            fit = fit_shift_map(coords[None], registered[None], units, weights[None])
        except InvalidInputError:
            continue
        source, used = name, int(np.count_nonzero(weights > 0))
        break
    if fit is not None and _explained(fit, registered, overlap) < MIN_EXPLAINED:
        fit, source, used = None, "registered (no map)", len(positions)
    if fit is None:
        nominal = registered
    else:
        linear = coords @ fit.matrix.T
        nominal = linear - linear[at_center[0]]
    deviation = float(np.max(np.hypot(*(registered - nominal).T)))
    shifts = {(p.row, p.col): (float(s[0]), float(s[1]))
              for p, s in zip(positions, nominal, strict=True)}
    return NominalShifts(shifts=shifts, source=source, fit=fit, positions_used=used,
                         deviation_px=deviation)
