"""Preprocessing of raw ``(C, H, W)`` PSF captures (:func:`prepare_psf`,
:meth:`GridCalibration.prepare`): background (the dark frame, else the manifest's black level),
hot pixels (dark-frame outliers, replaced by their 3 × 3 median), saturation (masked from
comparisons; a PSF whose bright region is more than ``max_saturated_fraction`` saturated is
refused unless ``allow_saturated``), exposure (scaled to the centre's) and a check that a
point-source signal is there. Normalization: ``"max"`` divides every PSF by the centre PSF's
peak, ``"sum"`` by its total, so relative gains are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfkit.errors import ConfigurationError, InvalidInputError, PositionRejected
from psfkit.io.grid import PsfGrid

LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)  # Rec. 709
NORMALIZATIONS = ("max", "sum")


@dataclass(frozen=True)
class PreprocessOptions:
    """How raw captures are turned into comparable PSFs (see the module docstring)."""

    normalization: str = "max"
    hot_pixel_sigma: float = 8.0
    saturation_level: float | None = None
    max_saturated_fraction: float = 0.01
    allow_saturated: bool = False
    min_snr: float = 10.0

    def __post_init__(self) -> None:
        if self.normalization not in NORMALIZATIONS:
            raise ConfigurationError(f"normalization must be one of {NORMALIZATIONS}, got "
                                     f"{self.normalization!r}")
        if self.hot_pixel_sigma <= 0 or self.min_snr <= 0:
            raise ConfigurationError("hot_pixel_sigma and min_snr must be positive")
        if not 0 <= self.max_saturated_fraction <= 1:
            raise ConfigurationError("max_saturated_fraction must be in [0, 1]")


@dataclass(frozen=True)
class PreparedPsf:
    """One preprocessed PSF: ``image`` ``(C, H, W)`` float32 (background subtracted, hot pixels
    repaired, at the reference exposure, not normalized), its ``(H, W)`` ``luminance`` and
    ``saturated`` mask."""

    image: np.ndarray
    luminance: np.ndarray
    saturated: np.ndarray
    n_saturated: int
    saturated_fraction: float
    snr: float


def luminance(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` luminance of a ``(C, H, W)`` image (Rec. 709 weights for RGB)."""
    if image.shape[0] == 1:
        return image[0]
    r, g, b = LUMINANCE_WEIGHTS
    if image.dtype != np.float32:
        return (r * image[0] + g * image[1] + b * image[2]).astype(np.float32, copy=False)
    # ``r·R + g·G + b·B`` with the same float32 operations in the same order, in two buffers
    out = np.multiply(image[0], r)
    term = np.multiply(image[1], g)
    out += term
    np.multiply(image[2], b, out=term)
    out += term
    return out


def saturation_level_for(grid: PsfGrid) -> float | None:
    """Raw value at which the grid's sensor saturates, from its dtype and ``bit_depth`` (``None``
    for float data). ``b``-bit data in a wider container is LSB-aligned (max 2^b − 1) or
    MSB-aligned (e.g. 65520 for 12 bits in 16): the centre image's maximum tells which."""
    if not np.issubdtype(grid.dtype, np.integer):
        return None
    container_bits = np.iinfo(grid.dtype).bits
    full = float(np.iinfo(grid.dtype).max)
    if grid.bit_depth is None or grid.bit_depth >= container_bits:
        return full
    lsb_max = 2.0**grid.bit_depth - 1
    centre = grid.center_index or (0, 0)
    if float(grid.load(*centre).max()) <= lsb_max:
        return lsb_max
    return lsb_max * 2.0 ** (container_bits - grid.bit_depth)


def clip_hint(natural: float | None) -> str:
    """The advice of a refused ``--saturation-level``, with the level that the images' type
    and ``bit_depth`` imply when there is one."""
    return "give the raw value at which the sensor clips" + (
        "" if natural is None else f" (the images' type and bit depth imply {natural:g})")


def check_saturation_level(level: float | None, grid: PsfGrid,
                           dark: np.ndarray | None) -> None:
    """Refuse (:class:`ConfigurationError`) a ``--saturation-level`` above the images' integer
    range (never reached) or at or below the background (the dark frame's median, else the
    ``black_level``, else the reference's darkest pixel: every pixel would count as saturated).
    """
    if level is None:
        return
    hint = clip_hint(saturation_level_for(grid))
    if np.issubdtype(grid.dtype, np.integer) and level > np.iinfo(grid.dtype).max:
        raise ConfigurationError(
            f"--saturation-level {level:g} exceeds {np.iinfo(grid.dtype).max}, the largest "
            f"value the {grid.dtype} images of {grid.root} can hold: saturation would never "
            f"be detected; {hint}")
    if dark is not None:   # the dark frame wins over the black level, as in prepare_psf
        background, what = float(np.median(dark)), f"the median of {grid.dark_file}"
    elif grid.black_level is not None:
        background, what = float(grid.black_level), f"the black_level of {grid.manifest_name}"
    else:
        centre = grid.require_center()
        background = float(np.min(grid.load(*centre)))
        what = f"the darkest pixel of {grid.position(*centre).file}"
    if level <= background:
        raise ConfigurationError(
            f"--saturation-level {level:g} is at or below the background of {grid.root} "
            f"({background:g}, {what}): every pixel would count as saturated; {hint}")


def check_background(grid: PsfGrid, dark: np.ndarray | None) -> None:
    """Refuse (:class:`InvalidInputError`, naming it) a background (the dark frame, else the
    ``black_level``) at or above the brightest pixel of a non-blank reference capture: nothing
    of any PSF would remain once it is subtracted."""
    if dark is None and grid.black_level is None:
        return
    centre = grid.require_center()
    reference = grid.load(*centre)
    brightest = float(np.max(reference))
    if brightest == float(np.min(reference)):   # a blank capture: it is to blame, not the level
        return
    if dark is not None:
        level, what = float(np.median(dark)), f"{grid.root / str(grid.dark_file)}: median"
    else:
        level, what = float(grid.black_level), f"{grid.root / grid.manifest_name}: black_level"
    if level >= brightest:
        raise InvalidInputError(
            f"{what} {level:g} is at or above the brightest pixel of the reference capture "
            f"{grid.position(*centre).file} ({brightest:g}): no PSF signal would remain after "
            "subtracting it; give the sensor's dark level")


def hot_pixel_mask(dark: np.ndarray, sigma: float = 8.0) -> np.ndarray:
    """``(H, W)`` mask of pixels that are outliers of the dark frame in any channel."""
    mask = np.zeros(dark.shape[1:], dtype=bool)
    for channel in dark:
        median = np.median(channel)
        spread = 1.4826 * np.median(np.abs(channel - median))
        spread = max(spread, 1e-6 * max(abs(float(median)), 1.0))
        mask |= channel > median + sigma * spread
    return mask


def repair_hot_pixels(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Replace masked pixels by the median of their 3 × 3 neighbourhood (other pixels kept)."""
    if not mask.any():
        return image
    out = image.copy()
    rows, cols = np.nonzero(mask)
    for c in range(image.shape[0]):
        padded = np.pad(image[c], 1, mode="edge")
        neighbours = np.stack([padded[rows + dr, cols + dc] for dr in range(3) for dc in range(3)
                               if (dr, dc) != (1, 1)])
        out[c, rows, cols] = np.median(neighbours, axis=0)
    return out


def background_noise(lum: np.ndarray) -> float:
    """Robust noise level (std) of the dark quarter of a background-subtracted ``(H, W)``
    luminance (estimated on every other pixel: plenty of samples, four times faster)."""
    sample = lum[::2, ::2]
    dark = sample[sample <= np.quantile(sample, 0.25)]
    spread = 1.4826 * float(np.median(np.abs(dark - np.median(dark))))
    if spread == 0:  # noise-free data (simulations, quantized floors): fall back to the std
        spread = float(np.std(dark))
    return max(spread, 1e-12 * max(float(np.max(np.abs(sample))), 1e-30))


def signal_peak(lum: np.ndarray) -> float:
    """Robust peak of a background-subtracted ``(H, W)`` luminance, whatever the PSF's size:
    the brighter of the 99.99th percentile of every other pixel (a caustic) and the faintest
    pixel of the brightest 2 × 2 block (a star of a few pixels); both ignore one hot pixel."""
    import cv2

    block = cv2.erode(np.ascontiguousarray(lum, dtype=np.float32), np.ones((2, 2), np.uint8),
                      borderType=cv2.BORDER_REPLICATE)
    return max(float(np.percentile(lum[::2, ::2], 99.99)), float(block.max()))


def prepare_psf(raw: np.ndarray, *, dark: np.ndarray | None = None,
                black_level: float | None = None, hot_pixels: np.ndarray | None = None,
                saturation_level: float | None = None, exposure_scale: float = 1.0,
                options: PreprocessOptions | None = None, name: str = "PSF",
                overwrite_raw: bool = False) -> PreparedPsf:
    """Preprocess one raw ``(C, H, W)`` capture.

    Parameters
    ----------
    dark, black_level : optional
        Background to subtract (the dark frame wins).
    hot_pixels : numpy.ndarray, optional
        ``(H, W)`` mask from :func:`hot_pixel_mask`.
    saturation_level : float, optional
        Raw value at which the sensor clips.
    exposure_scale : float
        Factor to the reference exposure.
    name : str
        File name for error messages.
    overwrite_raw : bool
        A float32 ``raw`` may be modified in place and returned (saves a copy).

    Raises
    ------
    PositionRejected
        NaN/Inf, too much saturated, or no point-source signal (``reason`` says which).
    ConfigurationError
        ``--saturation-level`` marks more pixels than the PSF has bright ones (the level is
        wrong, not the PSF).
    """
    options = options or PreprocessOptions()
    if np.issubdtype(raw.dtype, np.floating) and not np.all(np.isfinite(raw)):
        raise PositionRejected(f"{name}: contains {int(np.count_nonzero(~np.isfinite(raw)))} "
                               "NaN/Inf pixel value(s)", "non-finite")
    image = raw.astype(np.float32, copy=not overwrite_raw)
    level = options.saturation_level if options.saturation_level is not None \
        else saturation_level
    saturated = np.any(raw >= level, axis=0) if level is not None \
        else np.zeros(raw.shape[1:], dtype=bool)
    if dark is not None:
        image -= dark
    elif black_level is not None:
        image -= np.float32(black_level)
    if hot_pixels is not None:
        image = repair_hot_pixels(image, hot_pixels & ~saturated)
    if exposure_scale != 1.0:
        image *= np.float32(exposure_scale)
    lum = luminance(image)  # a view of ``image`` for mono data: scale before, not after
    noise = background_noise(lum)
    peak = signal_peak(lum)
    snr = peak / noise
    if not np.isfinite(snr) or snr < options.min_snr:
        raise PositionRejected(
            f"{name}: no point-source signal (peak/noise = {snr:.1f} < {options.min_snr:g}); "
            "empty or wrongly exposed capture", "no signal")
    n_saturated = int(saturated.sum())
    bright = int(np.count_nonzero(lum > 0.1 * peak)) or 1
    fraction = n_saturated / bright
    if fraction > 1 and options.saturation_level is not None:
        raise ConfigurationError(
            f"--saturation-level {level:g} marks {n_saturated} pixels of {name} saturated, "
            f"more than the {bright} bright pixels of its PSF (a sensor clips only where the "
            f"PSF is brightest); {clip_hint(saturation_level)}")
    if fraction > options.max_saturated_fraction and not options.allow_saturated:
        raise PositionRejected(
            f"{name}: {n_saturated} saturated pixels ({100 * fraction:.1f}% of the bright PSF, "
            f"limit {100 * options.max_saturated_fraction:g}%); lower the exposure, or pass "
            "--allow-saturated to mask them", "saturated")
    return PreparedPsf(image=image, luminance=lum, saturated=saturated,
                       n_saturated=n_saturated, saturated_fraction=fraction, snr=snr)


@dataclass(frozen=True)
class GridCalibration:
    """Per-grid preprocessing inputs shared by every position."""

    dark: np.ndarray | None
    black_level: float | None
    hot_pixels: np.ndarray | None
    saturation_level: float | None
    exposures: np.ndarray | None
    reference_exposure: float | None

    @classmethod
    def from_grid(cls, grid: PsfGrid, options: PreprocessOptions) -> GridCalibration:
        dark = grid.load_dark()
        check_background(grid, dark)                                   # before any PSF
        check_saturation_level(options.saturation_level, grid, dark)
        hot = hot_pixel_mask(dark, options.hot_pixel_sigma) if dark is not None else None
        exposures = grid.exposures()
        centre = grid.require_center()
        return cls(dark=dark, black_level=grid.black_level, hot_pixels=hot,
                   saturation_level=saturation_level_for(grid), exposures=exposures,
                   reference_exposure=None if exposures is None else float(exposures[centre]))

    def prepare(self, grid: PsfGrid, row: int, col: int,
                options: PreprocessOptions) -> PreparedPsf:
        """Load and preprocess the PSF at ``(row, col)``."""
        scale = 1.0
        if self.exposures is not None and self.reference_exposure is not None:
            scale = self.reference_exposure / float(self.exposures[row, col])
            if not 1e-6 <= scale <= 1e6:
                # blame the manifest's number, not the image it would scale to nothing
                raise InvalidInputError(
                    f"{grid.path(row, col)}: manifest exposure_s "
                    f"{float(self.exposures[row, col]):g} differs from the centre's "
                    f"({self.reference_exposure:g}) by more than 10^6x; check exposure_s")
        return prepare_psf(grid.load(row, col), dark=self.dark, black_level=self.black_level,
                           hot_pixels=self.hot_pixels, saturation_level=self.saturation_level,
                           exposure_scale=scale, options=options, name=str(grid.path(row, col)),
                           overwrite_raw=True)


def normalization_scale(reference: np.ndarray, normalization: str) -> float:
    """Divisor that brings the reference PSF to unit peak (``"max"``) or unit sum (``"sum"``)."""
    if normalization == "max":
        return float(np.max(reference))
    if normalization == "sum":
        return float(np.sum(reference))
    raise ConfigurationError(f"normalization must be one of {NORMALIZATIONS}")
