"""One measured point-source image as a shift-invariant kernel, and the one PSF loader
(:func:`load_psf_image`) of ``ekdun reconstruct`` and ``ekdun train --psf``."""

from __future__ import annotations

import numpy as np

from psfkit.errors import ConfigurationError, InvalidInputError

BACKGROUNDS = ("none", "corner")
CORNER = (slice(5, 15), slice(5, 15))   # the DiffuserCam tutorial's dark patch, rows/cols 5..14


def subtract_background(image: np.ndarray, background: str = "corner",
                        where: str = "image") -> np.ndarray:
    """``image`` ``(C, H, W)`` minus its background: ``"corner"`` subtracts each channel's mean
    over ``[5:15, 5:15]`` (as the DiffuserCam tutorial), ``"none"`` nothing.

    Raises
    ------
    ConfigurationError
        Unknown ``background``.
    InvalidInputError
        ``"corner"`` on an image smaller than 15 × 15 px (``where`` names it).
    """
    if background not in BACKGROUNDS:
        raise ConfigurationError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    if background == "none":
        return image
    h, w = image.shape[-2:]
    if min(h, w) < CORNER[0].stop:
        raise InvalidInputError(f"{where}: image of {h}x{w} px has no background corner (rows "
                                f"and columns {CORNER[0].start}..{CORNER[0].stop - 1}); use "
                                "--background none or a larger image")
    return image - image[(slice(None), *CORNER)].mean(axis=(1, 2), keepdims=True,
                                                       dtype=np.float64).astype(image.dtype)


def psf_kernel(image: np.ndarray, background: str = "corner", downsample: int = 1,
               where: str = "PSF") -> np.ndarray:
    """A point-source image ``(C, H, W)`` as a shift-invariant kernel: background subtracted,
    ``downsample``-binned (block mean), clipped to ``>= 0`` and each channel scaled to unit sum;
    ``(C, H // downsample, W // downsample)`` float32.

    Raises
    ------
    InvalidInputError
        A binning that leaves no pixel, or a channel without signal (``where`` names it).
    """
    from psfkit.numerics.resample import bin_mean

    if isinstance(downsample, bool) or not isinstance(downsample, int) or downsample < 1:
        raise ConfigurationError(f"downsample must be a positive integer, got {downsample!r}")
    if min(image.shape[-2:]) // downsample < 1:
        raise InvalidInputError(f"{where}: binning {image.shape[-2]}x{image.shape[-1]} by "
                                f"{downsample} leaves no pixel")
    image = subtract_background(np.asarray(image, dtype=np.float64), background, where)
    if downsample > 1:
        image = bin_mean(image, downsample)
    psf = np.clip(image, 0, None)
    sums = psf.sum(axis=(1, 2), keepdims=True)
    if not np.all(sums > 0):
        raise InvalidInputError(f"{where}: a channel of the PSF has no signal above the "
                                f"background ({background}); not a point-source image")
    return (psf / sums).astype(np.float32)


def load_psf_image(path: str, channel_order: str = "RGB", background: str = "corner",
                   downsample: int = 1, white_level: float | None = None) -> np.ndarray:
    """A point-source image file as a kernel: :func:`psfkit.io.images.read_image_float`, then
    :func:`psf_kernel`.

    Parameters
    ----------
    path : str
        ``.npy``, PNG or TIFF image of the point source, the sensor's size.
    channel_order : {"RGB", "BGR"}
        Of ``.npy``/TIFF files.
    white_level : float, optional
        Full-scale stored value of integer files.

    Raises
    ------
    InvalidInputError
        Unreadable file, NaN/Inf, or a channel without signal.
    """
    from psfkit.io.images import read_image_float

    return psf_kernel(read_image_float(path, channel_order, white_level), background,
                      downsample, str(path))
