"""The working copy of an aligned PSF grid: its region and binning (:func:`working_region`) and
the cropped, binned stack of aligned PSFs (:class:`WorkingStack`) the fits, CV and PCA use.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from psfkit.calibration.alignment import AlignedPsf
from psfkit.errors import InvalidInputError
from psfkit.fitting.grid.design import PixelFrame
from psfkit.fitting.grid.eigen import mask_rectangle
from psfkit.numerics.resample import bin_image, binning_factor


def working_region(support: np.ndarray, reference: np.ndarray, working_size: int
                   ) -> tuple[tuple[slice, slice] | None, int, dict[str, Any]]:
    """Where and at what binning the working copy holds the aligned PSFs, from the centre PSF.

    The region is the centre PSF's support box grown by its own size (and 8 px) on every side,
    clipped to the sensor; the binning the smallest bringing it to ``working_size`` px.

    Parameters
    ----------
    support : numpy.ndarray
        ``(H, W)`` bool support of the centre PSF.
    reference : numpy.ndarray
        ``(H, W)`` its luminance.
    working_size : int
        Longest side of the working copy, px.

    Returns
    -------
    region : (slice, slice) or None
        Rows and columns of the sensor (``None``: all of it).
    factor : int
        Binning factor.
    record : dict
        JSON-ready description (with the power the binning aliases).
    """
    h, w = support.shape
    rows, cols = np.flatnonzero(support.any(axis=1)), np.flatnonzero(support.any(axis=0))
    if len(rows) == 0:
        rows, cols = np.arange(h), np.arange(w)
    box = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    extent = [box[0].stop - box[0].start, box[1].stop - box[1].start]
    grown = tuple(slice(max(0, sl.start - size - 8), min(n, sl.stop + size + 8))
                  for sl, size, n in zip(box, extent, (h, w), strict=True))
    shape = (grown[0].stop - grown[0].start, grown[1].stop - grown[1].start)
    region = None if shape == (h, w) else (grown[0], grown[1])
    factor = binning_factor(shape, working_size)
    record = {"chosen_from": "the whole sensor (the PSF fills it)" if region is None else
              "the centre PSF's support",
              "origin_px": [0, 0] if region is None else [region[0].start, region[1].start],
              "shape_px": list(shape), "binning": factor, "psf_extent_px": extent,
              "aliased_power": aliased_power(reference[box], factor)}
    return region, factor, record


def aliased_power(image: np.ndarray, factor: int) -> float:
    """Fraction of an image's non-DC power above the Nyquist frequency of a grid binned by
    ``factor`` (0 for ``factor`` 1)."""
    import scipy.fft as sfft

    if factor <= 1 or min(image.shape) < 2:
        return 0.0
    power = np.abs(sfft.rfft2(image - image.mean(), workers=-1)) ** 2
    gy = np.abs(np.fft.fftfreq(image.shape[0]))[:, None]
    gx = np.fft.rfftfreq(image.shape[1])[None, :]
    total = float(power.sum())
    limit = 0.5 / factor
    return float(power[(gy > limit) | (gx > limit)].sum()) / total if total > 0 else 0.0


@dataclass
class WorkingStack:
    """The aligned grid cropped to ``region`` (``None``: the whole sensor) and binned by ``factor``.

    Per measured position: ``images`` ``(P, C, h, w)``, ``valid`` ``(P, h, w)``, ``shifts``
    ``(P, 2)`` binned px, ``index`` ``(P, 2)`` grid row/column, ``overlap`` ``(P,)`` (the centre
    PSF's light in its registered overlap), ``gains``, ``light_in_region`` ``(P,)``.
    """

    factor: int
    images: np.ndarray
    valid: np.ndarray
    shifts: np.ndarray
    index: np.ndarray
    overlap: np.ndarray
    gains: np.ndarray
    region: tuple[slice, slice] | None = None
    sensor_shape: tuple[int, int] | None = None
    light_in_region: np.ndarray | None = None

    @classmethod
    def empty(cls, n: int, image_shape: tuple[int, int, int], factor: int,
              region: tuple[slice, slice] | None = None) -> WorkingStack:
        c, h, w = image_shape
        if region is not None:
            h, w = region[0].stop - region[0].start, region[1].stop - region[1].start
        shape = (h // factor, w // factor)
        return cls(factor=factor, images=np.zeros((n, c, *shape), np.float32),
                   valid=np.zeros((n, *shape), bool), shifts=np.zeros((n, 2)),
                   index=np.zeros((n, 2), int), overlap=np.zeros(n), gains=np.zeros(n),
                   region=region, sensor_shape=tuple(image_shape[1:]),   # type: ignore[arg-type]
                   light_in_region=np.ones(n))

    @property
    def frame(self) -> PixelFrame | None:
        """Where the working pixels lie on the sensor (``None``: the whole sensor binned)."""
        if self.region is None or self.sensor_shape is None:
            return None
        return PixelFrame.crop(self.sensor_shape, (self.region[0].start, self.region[1].start),
                               self.factor, self.images.shape[-2:])

    def reduce(self, image: np.ndarray) -> np.ndarray:
        """A full-resolution ``(..., H, W)`` image cropped to ``region`` and block-averaged."""
        if self.region is not None:
            image = image[(..., *self.region)]
        return bin_image(image, self.factor) / self.factor**2

    def subset(self, members: np.ndarray) -> WorkingStack:
        """The stack of the ``members`` (bool ``(P,)``) only (the same arrays when all)."""
        if members.all():
            return self
        per_position = ("images", "valid", "shifts", "index", "overlap", "gains",
                        "light_in_region")
        return dataclasses.replace(self, **{name: getattr(self, name)[members]
                                            for name in per_position
                                            if getattr(self, name) is not None})

    def row_of(self, index: tuple[int, int]) -> int:
        """The stack entry of grid index ``(row, col)``."""
        hits = np.flatnonzero((self.index == np.asarray(index)).all(axis=1))
        if len(hits) == 0:
            raise InvalidInputError(f"grid index {index} is not among the measured positions")
        return int(hits[0])

    def lattice(self, values: np.ndarray, grid_shape: tuple[int, int]) -> np.ndarray:
        """Per-entry ``values`` ``(P, ...)`` on the ``(N, M, ...)`` lattice (NaN elsewhere)."""
        out = np.full((*grid_shape, *np.shape(values)[1:]), np.nan)
        out[self.index[:, 0], self.index[:, 1]] = values
        return out

    def put(self, p: int, aligned: AlignedPsf, image: np.ndarray, gain: float) -> None:
        """Store position ``p`` cropped and binned (``image`` may be gain-compensated)."""
        f = self.factor
        valid = aligned.valid
        if self.region is not None:
            image, valid = image[(slice(None), *self.region)], valid[self.region]
            if self.light_in_region is not None and aligned.support is not None:
                light = np.where(aligned.support, np.maximum(aligned.luminance, 0.0), 0.0)
                total = float(light.sum(dtype=np.float64))
                self.light_in_region[p] = float(light[self.region].sum(dtype=np.float64)) \
                    / total if total > 0 else 1.0
        self.images[p] = bin_image(image, f)
        self.images[p] /= np.float32(f**2)
        rect = mask_rectangle(valid)
        if rect is None:
            self.valid[p] = bin_image(valid.astype(np.float32), f) > f**2 - 0.5
        else:   # the blocks that lie inside the rectangle
            h, w = self.valid.shape[1:]
            rows = (np.arange(h) * f >= rect[0].start) & ((np.arange(h) + 1) * f <= rect[0].stop)
            cols = (np.arange(w) * f >= rect[1].start) & ((np.arange(w) + 1) * f <= rect[1].stop)
            self.valid[p] = rows[:, None] & cols[None, :]
        self.shifts[p] = np.asarray(aligned.shift) / f
        self.index[p] = (aligned.position.row, aligned.position.col)
        self.overlap[p] = aligned.support_overlap if np.isfinite(aligned.support_overlap) \
            else aligned.overlap
        self.gains[p] = gain
