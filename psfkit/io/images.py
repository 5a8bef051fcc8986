"""Reading and writing single images (TIFF, PNG, NumPy): ``(H, W[, C])`` on disk (planar
TIFFs recognised), ``(C, H, W)`` in memory; only this module converts between the two."""

from __future__ import annotations

import contextlib
import logging
import logging.handlers
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from psfkit.errors import InvalidInputError
from psfkit.io.atomic import atomic_file
from psfkit.io.png import decode_png, png_declared_shape
from psfkit.io.validation import bounded_size, check_array_shape, npy_header, require_finite_output

IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".npy")


def _to_chw(array: np.ndarray, path: Path, channels_last: bool = True) -> np.ndarray:
    if array.ndim == 2:
        return array[None]
    if array.ndim != 3:
        raise InvalidInputError(f"{path}: expected a 2-D or 3-D image, got shape {array.shape}")
    chw = np.moveaxis(array, -1, 0) if channels_last else array
    if chw.shape[0] not in (1, 3):
        raise InvalidInputError(
            f"{path}: has {chw.shape[0]} channels; expected 1 (mono) or 3 (RGB)")
    return chw


@contextlib.contextmanager
def collected_log(name: str | None = None, level: int = logging.NOTSET
                  ) -> Iterator[list[logging.LogRecord]]:
    """Within the block, the records of logger ``name`` (default: the root) at ``level`` or
    above are collected (yielded) instead of printed; e.g. what tifffile says of a damaged file,
    for the one error line."""
    handler = logging.handlers.BufferingHandler(capacity=sys.maxsize)   # never flushed
    handler.setLevel(level)
    logger = logging.getLogger(name)
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield handler.buffer
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _check_declared_size(shape: tuple[int, ...], path: Path, dtype: object = None) -> None:
    """Refuse an image whose header declares an absurd size, before decoding it."""
    shape = tuple(int(s) for s in shape)
    if len(shape) not in (2, 3):
        raise InvalidInputError(f"{path}: expected a 2-D or 3-D image, got shape {shape}")
    if len(shape) == 3 and min(shape[0], shape[2]) > 4:
        raise InvalidInputError(f"{path}: shape {list(shape)} has no colour axis of 1 or 3 "
                                "channels (a stack of pages or planes is not an image)")
    height, width = (shape[1], shape[2]) if len(shape) == 3 and shape[0] <= 4 < shape[2] \
        else (shape[0], shape[1])
    bounded_size((height, width), f"{path}: image size", unit="pixels")
    check_array_shape(shape, dtype, str(path))


def read_image(path: str | os.PathLike, channel_order: str = "RGB",
               dtype: np.dtype | type | None = None) -> np.ndarray:
    """Read one image file as a ``(C, H, W)`` array in its stored dtype.

    Parameters
    ----------
    path : path-like
        ``.tif``/``.tiff`` (tifffile), ``.png`` (OpenCV, 8 or 16 bit) or ``.npy``.
    channel_order : {"RGB", "BGR"}
        Channel order of ``.npy``/TIFF files (converted to RGB); PNG is always RGB.
    dtype : numpy dtype, optional
        Convert in the same pass as the reordering (one copy); default: as stored.

    Returns
    -------
    numpy.ndarray
        ``(C, H, W)`` with ``C`` in {1, 3}, dtype as stored (or ``dtype``).

    Raises
    ------
    InvalidInputError
        Missing file, unknown extension, or content that is not a 1- or 3-channel image.
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if channel_order not in ("RGB", "BGR"):
        raise InvalidInputError(f"channel_order must be 'RGB' or 'BGR', got {channel_order!r}")
    if suffix == ".png":
        channel_order = "RGB"              # decoded to RGB whatever the manifest says
    if suffix == ".npy":
        # a .npy image keeps its stored dtype (the header's wins over the requested
        # ``dtype``), so that the numbers computed from existing .npy data stay the same
        dtype = None
    try:
        if suffix not in _DECODERS:
            raise InvalidInputError(
                f"{path}: unsupported image type '{suffix}' (use {', '.join(IMAGE_SUFFIXES)})")
        chw = _DECODERS[suffix](path)
    except InvalidInputError:
        raise
    except Exception as exc:  # any decoder failure means "not an image we can read"
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InvalidInputError(f"{path}: not a readable image ({reason})") from None
    if not (np.issubdtype(chw.dtype, np.integer) or np.issubdtype(chw.dtype, np.floating)):
        raise InvalidInputError(f"{path}: unsupported pixel type {chw.dtype}")
    if channel_order == "BGR" and chw.shape[0] == 3:
        chw = chw[::-1]
    if chw.flags.c_contiguous:
        return chw if dtype is None else chw.astype(dtype, copy=False)
    # one plane at a time: twice as fast as a strided (H, W, C) → (C, H, W) copy at once
    out = np.empty(chw.shape, dtype=chw.dtype if dtype is None else dtype)
    for c, plane in enumerate(chw):
        out[c] = plane
    return out


def _decode_tiff(path: Path) -> np.ndarray:
    import tifffile

    with collected_log("tifffile") as records, tifffile.TiffFile(path) as tif:
        if not tif.series:
            said = records[0].getMessage().split("> ", 1)[-1] if records else "no image data"
            raise InvalidInputError(f"{path}: not a readable image ({said})")
        series = tif.series[0]
        _check_declared_size(series.shape, path, series.dtype)
        array = series.asarray()
        axes = series.axes
    channels_last = not (array.ndim == 3 and axes.startswith(("S", "C")))
    return _to_chw(array, path, channels_last)


def _decode_png(path: Path) -> np.ndarray:
    """RGB whatever the channel order asked for (OpenCV decodes to BGR)."""
    height, width, channels = png_declared_shape(path)
    _check_declared_size((height, width, channels), path, np.uint16)
    array = decode_png(path)
    if array.ndim == 3 and array.shape[2] == 3:
        array = array[..., ::-1]
    return _to_chw(array, path)


def _decode_npy(path: Path) -> np.ndarray:
    with open(path, "rb") as fh:     # the header only: the size is checked first
        shape, _, dtype = npy_header(fh, str(path))
    _check_declared_size(shape, path, dtype)
    return _to_chw(np.load(path, allow_pickle=False), path)


#: The decoder of each image suffix: the image as stored, ``(C, H, W)``.
_DECODERS: dict[str, Callable[[Path], np.ndarray]] = {
    ".tif": _decode_tiff, ".tiff": _decode_tiff, ".png": _decode_png, ".npy": _decode_npy}


def unit_range(image: np.ndarray, where: str, white_level: float | None = None) -> np.ndarray:
    """An image as float32 in the toolkit's units (``docs/inputs-and-errors.md``): integer
    data divided by ``white_level`` (default the dtype's maximum), float data kept.

    Parameters
    ----------
    image : numpy.ndarray
        ``(C, H, W)`` as read by :func:`read_image`.
    where : str
        Names the file in messages.
    white_level : float, optional
        Stored value of full scale, e.g. 4095 for 12-bit data in 16-bit files.

    Returns
    -------
    numpy.ndarray
        float32, same shape, finite (NaN/Inf or a bad white level: InvalidInputError).
    """
    if np.issubdtype(image.dtype, np.integer):
        level = float(np.iinfo(image.dtype).max) if white_level is None else float(white_level)
        if not (np.isfinite(level) and 0 < level <= 2.0**32):
            raise InvalidInputError(f"{where}: white level must be a number in (0, 2^32], got "
                                    f"{white_level!r}")
        # float32 ÷ float32 is correctly rounded: q/255 from an 8-bit file and 257·q/65535
        # from the same values in a 16-bit file give the same float32, bit for bit
        out = image.astype(np.float32)
        out /= np.float32(level)
        return out
    out = image.astype(np.float32, copy=False)
    bad = int(np.count_nonzero(~np.isfinite(out)))
    if bad:
        raise InvalidInputError(f"{where}: contains NaN/Inf values ({bad} of them)")
    return out


def read_image_float(path: str | os.PathLike, channel_order: str = "RGB",
                     white_level: float | None = None) -> np.ndarray:
    """:func:`read_image` then :func:`unit_range`: ``(C, H, W)`` float32 RGB in the toolkit's
    units, the same numbers for a file in any format, whichever command reads it."""
    return unit_range(read_image(path, channel_order), str(path), white_level)


def write_image(path: str | os.PathLike, image: np.ndarray, compress: bool = False) -> Path:
    """Write a ``(C, H, W)`` array atomically as TIFF, PNG (uint8/uint16 only) or ``.npy``;
    ``compress``: deflate-compress a TIFF (lossless)."""
    path = Path(path)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[0] not in (1, 3):
        raise InvalidInputError(f"{path}: expected a (C, H, W) array with C in (1, 3), "
                                f"got shape {image.shape}")
    require_finite_output(image, str(path))
    hwc = image[0] if image.shape[0] == 1 else np.moveaxis(image, 0, -1)
    suffix = path.suffix.lower()
    with atomic_file(path) as tmp:
        if suffix in (".tif", ".tiff"):
            import tifffile

            photometric = "rgb" if hwc.ndim == 3 else "minisblack"
            tifffile.imwrite(tmp, np.ascontiguousarray(hwc), photometric=photometric,
                             compression="zlib" if compress else None)
        elif suffix == ".png":
            import cv2

            if hwc.dtype not in (np.uint8, np.uint16):
                raise InvalidInputError(f"{path}: PNG needs uint8 or uint16 data, got {hwc.dtype}")
            data = hwc[..., ::-1] if hwc.ndim == 3 else hwc
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(data)):
                raise InvalidInputError(f"{path}: OpenCV failed to encode the PNG")
        elif suffix == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, np.ascontiguousarray(hwc), allow_pickle=False)
        else:
            raise InvalidInputError(
                f"{path}: unsupported image type '{suffix}' (use {', '.join(IMAGE_SUFFIXES)})")
    return path
