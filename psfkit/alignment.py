"""Bring every PSF of a grid into the centre PSF's frame: preprocess, register, align.

Shared by the characterization (:mod:`psfkit.characterize`) and the eigen-kernel fit
(:mod:`psfkit.eigen`), so that both see exactly the same registered PSFs.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from psfkit.errors import InvalidInputError
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
    register_shift,
    shift_image,
)

MIN_OVERLAP = 0.05       # below this fraction of the sensor, a position cannot be compared
RELIABLE_OVERLAP = 0.5   # below this, a PSF is mostly off the sensor: shift and warp less
                         # reliable (its deformation biases a translation-only registration)


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

    @cached_property
    def luminance(self) -> np.ndarray:
        """``(H, W)`` luminance of ``image`` (computed on first use: the eigen-kernel fit
        never needs it)."""
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
    """

    def __init__(self, grid: PsfGrid, options: PreprocessOptions | None = None,
                 upsample: int = 100) -> None:
        self.grid = grid
        self.options = options or PreprocessOptions()
        self.upsample = upsample
        self.center = grid.require_center()
        self.calibration = GridCalibration.from_grid(grid, self.options)
        self.reference_prepared = self.calibration.prepare(grid, *self.center, self.options)
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
        InvalidInputError
            The PSF cannot be registered, or overlaps the centre PSF too little (message
            names the file).
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
                    raise InvalidInputError(f"{name}: cannot register to the centre PSF "
                                            f"({exc})") from None
        aligned, valid = shift_image(image, shift)
        if prep.n_saturated:
            sat_aligned, _ = shift_image(prep.saturated.astype(np.float32), shift)
            valid &= sat_aligned < 0.5
        valid &= self._unsaturated
        overlap = float(valid.mean())
        if overlap < MIN_OVERLAP:
            raise InvalidInputError(f"{name}: overlaps the centre PSF on only "
                                    f"{100 * overlap:.1f}% of the sensor after registration; "
                                    "cannot compare")
        return AlignedPsf(position=pos, image=aligned, valid=valid, shift=shift, prepared=prep)
