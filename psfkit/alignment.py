"""Bring every PSF of a grid into the centre PSF's frame: preprocess, register, align.

Shared by the characterization (:mod:`psfkit.characterize`) and the eigen-kernel fit
(:mod:`psfkit.eigen`), so that both see exactly the same registered PSFs.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from psfkit.errors import InvalidInputError, PositionRejected
from psfkit.io.grid import GridPosition, PsfGrid
from psfkit.preprocess import (
    GridCalibration,
    PreparedPsf,
    PreprocessOptions,
    luminance,
    normalization_scale,
)
from psfkit.registration import (
    ShiftRegistrar,
    high_frequency_fraction,
    normalized_cross_correlation,
    register_shift,
    shift_image,
)

MIN_OVERLAP = 0.05       # below this fraction of the sensor, a position cannot be compared
RELIABLE_OVERLAP = 0.5   # below this, a PSF is mostly off the sensor: shift and warp less
                         # reliable (its deformation biases a translation-only registration)
#: Default lowest registration quality (NCC with the centre PSF after alignment) of a usable
#: position; below it the position is excluded ("low NCC"). The virtual bench's 9 × 9 grids
#: reach 0.95 at the corners; a capture of the wrong thing scores near 0.
MIN_QUALITY = 0.5
#: Why a position can be excluded (:class:`~psfkit.errors.PositionRejected`.reason).
REJECTION_REASONS = {
    "saturated": "too much of the PSF saturated",
    "no signal": "no point-source signal above the noise (empty or badly exposed capture)",
    "non-finite": "NaN/Inf pixel values",
    "registration failed": "cannot be registered to the reference PSF",
    "no overlap": "overlaps the reference PSF on too little of the sensor",
    "low NCC": "registration quality (NCC with the reference PSF) below the threshold",
}


@dataclass(frozen=True)
class ExcludedPosition:
    """A captured position left out of the analyses, with its reason (a key of
    :data:`REJECTION_REASONS`) and the one-line detail."""

    row: int
    col: int
    file: str
    reason: str
    detail: str
    field_deg: tuple[float, float] | None = None
    monitor_px: tuple[float, float] | None = None

    @classmethod
    def of(cls, pos: GridPosition, exc: PositionRejected) -> ExcludedPosition:
        return cls(row=pos.row, col=pos.col, file=pos.file, reason=exc.reason,
                   detail=str(exc), field_deg=pos.field_deg, monitor_px=pos.monitor_px)

    def to_dict(self) -> dict[str, Any]:
        return {"row": self.row, "col": self.col, "file": self.file, "reason": self.reason,
                "detail": self.detail, "field_deg": self.field_deg,
                "monitor_px": self.monitor_px}


@dataclass(frozen=True)
class AlignedPsf:
    """One grid PSF in the centre PSF's frame.

    ``image`` is ``(C, H, W)`` float32 in the grid's normalization (centre PSF peak or total
    = 1), displaced back by ``shift`` so that it overlays the centre PSF; ``valid`` marks the
    pixels that hold data (inside the sensor and unsaturated in both PSFs).
    """

    position: GridPosition
    image: np.ndarray
    valid: np.ndarray
    shift: tuple[float, float]
    prepared: PreparedPsf
    quality: float = float("nan")   # NCC with the reference luminance over ``valid``

    @cached_property
    def luminance(self) -> np.ndarray:
        """``(H, W)`` luminance of ``image`` (:meth:`GridAligner.align` fills it in: the
        quality check needs it)."""
        return luminance(self.image)

    @property
    def overlap(self) -> float:
        return float(self.valid.mean())


class GridAligner:
    """Registers and aligns the PSFs of one grid to its centre PSF.

    Parameters
    ----------
    grid : PsfGrid
    options : PreprocessOptions
    upsample : int
        Registration precision ``1/upsample`` px.
    min_quality : float
        Lowest registration quality (NCC) of a usable position (0: no check).
    strict : bool
        :meth:`try_align` raises for a bad position instead of excluding it.

    Raises
    ------
    InvalidInputError
        The reference (centre) PSF is unusable: one line naming it, its problem, and
        ``--reference``.
    """

    def __init__(self, grid: PsfGrid, options: PreprocessOptions | None = None,
                 upsample: int = 100, min_quality: float = MIN_QUALITY,
                 strict: bool = False) -> None:
        self.grid = grid
        self.options = options or PreprocessOptions()
        self.upsample = upsample
        self.min_quality = min_quality
        self.strict = strict
        self.center = grid.require_center()
        self.calibration = GridCalibration.from_grid(grid, self.options)
        try:
            self.reference_prepared = self.calibration.prepare(grid, *self.center, self.options)
        except PositionRejected as exc:
            if strict:
                raise
            raise InvalidInputError(
                f"{exc}; this is the reference (centre) PSF {grid.describe_index(self.center)}, "
                "which every position is compared with: fix it, or name another captured "
                "position with --reference R,C") from None
        self.scale = normalization_scale(self.reference_prepared.image,
                                         self.options.normalization)
        self.reference = self.reference_prepared.image / np.float32(self.scale)
        self.reference_luminance = self.reference_prepared.luminance / np.float32(self.scale)
        self._unsaturated = ~self.reference_prepared.saturated
        self._allow_binning = high_frequency_fraction(self.reference_luminance) < 0.01
        self._registrar = ShiftRegistrar(self.reference_luminance, upsample,
                                         allow_binning=self._allow_binning)

    def register(self, reference: np.ndarray, moving: np.ndarray) -> tuple[float, float]:
        """Shift of ``moving`` relative to ``reference`` with this grid's settings."""
        return register_shift(reference, moving, upsample=self.upsample,
                              allow_binning=self._allow_binning)

    def align(self, pos: GridPosition, shift: tuple[float, float] | None = None) -> AlignedPsf:
        """Preprocess, register (unless ``shift`` is given) and align one PSF.

        Raises
        ------
        PositionRejected
            The PSF fails a quality check (:data:`REJECTION_REASONS`): the message names the
            file, ``reason`` the check.
        """
        name = str(self.grid.root / pos.file)
        here = (pos.row, pos.col)
        prep = self.reference_prepared if here == self.center else \
            self.calibration.prepare(self.grid, pos.row, pos.col, self.options)
        image = prep.image / np.float32(self.scale)
        lum = prep.luminance / np.float32(self.scale)
        if shift is None:
            if here == self.center:
                shift = (0.0, 0.0)
            else:
                try:
                    shift = self._registrar.register(lum)
                except InvalidInputError as exc:
                    raise PositionRejected(f"{name}: cannot register to the centre PSF "
                                           f"({exc})", "registration failed") from None
        aligned, valid = shift_image(image, shift)
        if prep.n_saturated:
            sat_aligned, _ = shift_image(prep.saturated.astype(np.float32), shift)
            valid &= sat_aligned < 0.5
        valid &= self._unsaturated
        overlap = float(valid.mean())
        if overlap < MIN_OVERLAP:
            raise PositionRejected(f"{name}: overlaps the centre PSF on only "
                                   f"{100 * overlap:.1f}% of the sensor after registration; "
                                   "cannot compare", "no overlap")
        aligned_luminance = luminance(aligned)
        quality = normalized_cross_correlation(self.reference_luminance, aligned_luminance,
                                               valid)
        if quality < self.min_quality and here != self.center:
            raise PositionRejected(f"{name}: registration quality (NCC with the centre PSF) "
                                   f"{quality:.3f} below {self.min_quality:g}; not the same "
                                   "PSF pattern (wrong capture?)", "low NCC")
        item = AlignedPsf(position=pos, image=aligned, valid=valid, shift=shift, prepared=prep,
                          quality=quality)
        item.__dict__["luminance"] = aligned_luminance    # the cached property, computed once
        return item

    def try_align(self, pos: GridPosition) -> AlignedPsf | ExcludedPosition:
        """:meth:`align`, or the :class:`ExcludedPosition` of a PSF that fails a quality check
        (``strict``: the error propagates)."""
        try:
            return self.align(pos)
        except PositionRejected as exc:
            if self.strict:
                raise
            return ExcludedPosition.of(pos, exc)
