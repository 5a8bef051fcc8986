"""Bring every PSF of a grid into the centre PSF's frame: preprocess, register, align (shared
by the characterization and the eigen-kernel fit, so both see the same registered PSFs)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

import numpy as np

from psfkit.calibration.preprocess import (
    GridCalibration,
    PreparedPsf,
    PreprocessOptions,
    luminance,
    normalization_scale,
)
from psfkit.calibration.registration import (
    ShiftRegistrar,
    high_frequency_fraction,
    normalized_cross_correlation,
    psf_region,
    register_shift,
    shift_image,
)
from psfkit.errors import InvalidInputError, PositionRejected
from psfkit.io.grid import GridPosition, PsfGrid

MIN_OVERLAP = 0.05       # below this fraction of the centre PSF's light in the registered
                         # overlap, a position cannot be compared
RELIABLE_OVERLAP = 0.5   # below this, a PSF is mostly off the sensor: shift and warp less
                         # reliable (its deformation biases a translation-only registration)
#: The support of a PSF (:func:`psf_support`): where its luminance, smoothed by
#: ``SUPPORT_SMOOTHING_PX``, exceeds ``SUPPORT_FRACTION`` of its peak and ``SUPPORT_NOISE``
#: times the smoothed noise, grown by ``SUPPORT_MARGIN_PX``. Measured in pixels of the PSF,
#: never of the frame: a star's support is the same on a 1024² frame and on a 63² cut-out,
#: a caustic's covers most of the sensor.
SUPPORT_FRACTION = 0.01
SUPPORT_NOISE = 6.0
SUPPORT_SMOOTHING_PX = 1.0
SUPPORT_MARGIN_PX = 3
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
    "no overlap": "too little of the reference PSF's light lies in the registered overlap",
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
        return asdict(self)


#: Share of the sensor the centre PSF's support must cover for the PSF to count as filling it
#: (a caustic; :meth:`GridAligner.gain_region`). The bench caustic's covers 29 %; a 3 px star's,
#: with its margin, 0.1 % of a 320² frame and about 10 % of a 41² cut-out (whose numbers must
#: stay those of the full frame).
FILLING_SUPPORT = 0.2


@dataclass(frozen=True)
class AlignedPsf:
    """One grid PSF in the centre PSF's frame: ``image`` ``(C, H, W)`` float32 in the grid's
    normalization, displaced back by ``shift``; ``valid`` the pixels holding data (on the sensor,
    unsaturated in both PSFs)."""

    position: GridPosition
    image: np.ndarray
    valid: np.ndarray
    shift: tuple[float, float]
    prepared: PreparedPsf
    quality: float = float("nan")   # NCC with the reference luminance over ``compared``
    support: np.ndarray | None = None   # (H, W) bool: this PSF's support or the reference's
    support_overlap: float = float("nan")   # the reference's light inside ``valid``

    @property
    def compared(self) -> np.ndarray:
        """``(H, W)`` bool, the pixels the comparisons use: either PSF's support inside
        ``valid``."""
        return self.valid if self.support is None else self.valid & self.support

    @cached_property
    def luminance(self) -> np.ndarray:
        """``(H, W)`` luminance of ``image`` (filled in by :meth:`GridAligner.align`)."""
        return luminance(self.image)

    @property
    def overlap(self) -> float:
        """Fraction of the sensor where both PSFs hold data (not reliability: see
        ``support_overlap``)."""
        return float(self.valid.mean())


def psf_support(lum: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` bool support of a PSF ``lum`` ``(H, W)``, whatever its size or the frame's.

    The luminance smoothed by ``SUPPORT_SMOOTHING_PX`` above both ``SUPPORT_FRACTION`` of its
    peak and ``SUPPORT_NOISE`` × the noise, grown by ``SUPPORT_MARGIN_PX``; the brightest pixel
    always belongs. The noise: 1.4826 × MAD of the pixels (inside ``valid``, if given) farther
    than ``4 × SUPPORT_MARGIN_PX`` from those above the fraction (none: the fraction alone).
    """
    import cv2

    smooth = cv2.GaussianBlur(np.ascontiguousarray(lum, dtype=np.float32), (0, 0),
                              SUPPORT_SMOOTHING_PX, borderType=cv2.BORDER_REFLECT)
    peak = float(smooth.max())
    core = (smooth >= SUPPORT_FRACTION * peak).astype(np.uint8)
    size = 8 * SUPPORT_MARGIN_PX + 1          # a square: separable, fast at full resolution
    away = cv2.dilate(core, np.ones((size, size), np.uint8)) == 0
    if valid is not None:       # not the zeros outside an aligned PSF's data (and its edge)
        away &= cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    sample = smooth[::2, ::2][away[::2, ::2]]       # plenty of samples, a quarter of the work
    noise = 0.0
    if sample.size >= 64:
        noise = 1.4826 * float(np.median(np.abs(sample - np.median(sample))))
    threshold = min(max(SUPPORT_FRACTION * peak, SUPPORT_NOISE * noise), peak)
    size = 2 * SUPPORT_MARGIN_PX + 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return cv2.dilate((smooth >= threshold).astype(np.uint8), disk).astype(bool)


def support_overlap(reference_light: np.ndarray, valid: np.ndarray) -> float:
    """Fraction of the reference PSF's light (:attr:`GridAligner.reference_light`) inside
    ``valid``, the registered overlap."""
    total = float(np.sum(reference_light, dtype=np.float64))
    if total <= 0:
        return float(valid.mean())
    return float(np.sum(reference_light, where=valid, dtype=np.float64)) / total


class GridAligner:
    """Registers and aligns the PSFs of one grid to its centre PSF.

    ``upsample``: precision ``1/upsample`` px; ``min_quality``: lowest NCC of a usable position
    (0: no check); ``strict``: :meth:`try_align` raises instead of excluding.

    Raises
    ------
    InvalidInputError
        The reference (centre) PSF is unusable (names it, its problem, and ``--reference``).
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
        self._check_reference_unsaturated(grid)
        self.scale = normalization_scale(self.reference_prepared.image,
                                         self.options.normalization)
        self.reference = self.reference_prepared.image / np.float32(self.scale)
        self.reference_luminance = self.reference_prepared.luminance / np.float32(self.scale)
        self._unsaturated = ~self.reference_prepared.saturated
        self.reference_support = psf_support(self.reference_luminance)
        self.fills_sensor = float(self.reference_support.mean()) >= FILLING_SUPPORT
        self.reference_light = np.where(self.reference_support,
                                        np.maximum(self.reference_luminance, 0.0), 0.0)
        self._allow_binning = high_frequency_fraction(self.reference_luminance) < 0.01
        # a compact PSF is refined around itself, whatever the frame's size
        self._registrar = ShiftRegistrar(self.reference_luminance, upsample,
                                         allow_binning=self._allow_binning,
                                         region=psf_region(self.reference_support))

    def gain_region(self, aligned: AlignedPsf) -> np.ndarray:
        """``(H, W)`` bool, the pixels a position's gain is summed over: ``aligned.compared``
        for a compact PSF; the whole overlap for one that fills the sensor
        (:data:`FILLING_SUPPORT`), whose faint light is part of it (leaving it out biases the
        bench caustic's cos-law exponent by 6σ)."""
        return aligned.valid if self.fills_sensor else aligned.compared
    def _check_reference_unsaturated(self, grid: PsfGrid) -> None:
        """Refuse a reference whose saturated pixels leave less than :data:`MIN_OVERLAP`."""
        saturated = self.reference_prepared.saturated
        if float(np.mean(~saturated)) >= MIN_OVERLAP:
            return
        name = grid.root / grid.position(*self.center).file
        raise InvalidInputError(
            f"{name}: {int(saturated.sum())} of its {saturated.size} pixels are saturated, "
            "and masking them (--allow-saturated) leaves nothing to compare with; this is the "
            f"reference (centre) PSF {grid.describe_index(self.center)}: lower the exposure, "
            "or name another captured position with --reference R,C")

    def register(self, reference: np.ndarray, moving: np.ndarray) -> tuple[float, float]:
        """Shift of ``moving`` relative to ``reference`` with this grid's settings."""
        return register_shift(reference, moving, upsample=self.upsample,
                              allow_binning=self._allow_binning)

    def align(self, pos: GridPosition, shift: tuple[float, float] | None = None,
              check_quality: bool = True) -> AlignedPsf:
        """Preprocess, register (unless ``shift`` is given) and align one PSF.

        ``check_quality=False`` skips the NCC check (still measured): for a position already
        accepted and now aligned at another shift.

        Raises
        ------
        PositionRejected
            A failed quality check (:data:`REJECTION_REASONS`), naming the file.
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
        # reliability in terms of the PSF, not of the sensor: a star near the edge of a large
        # frame overlaps the centre star on little of the sensor but is all there
        covered = support_overlap(self.reference_light, valid)
        if covered < MIN_OVERLAP:
            raise PositionRejected(f"{name}: only {100 * covered:.1f}% of the centre PSF's "
                                   "light lies in the registered overlap; cannot compare",
                                   "no overlap")
        aligned_luminance = luminance(aligned)
        support = self.reference_support if here == self.center else \
            self.reference_support | psf_support(aligned_luminance, valid)
        quality = normalized_cross_correlation(self.reference_luminance, aligned_luminance,
                                               valid & support)
        if check_quality and quality < self.min_quality and here != self.center:
            raise PositionRejected(f"{name}: registration quality (NCC with the centre PSF) "
                                   f"{quality:.3f} below {self.min_quality:g}; not the same "
                                   "PSF pattern (wrong capture?)", "low NCC")
        item = AlignedPsf(position=pos, image=aligned, valid=valid, shift=shift, prepared=prep,
                          quality=quality, support=support, support_overlap=covered)
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
