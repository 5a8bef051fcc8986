"""Validation at the boundaries: the limits (``MAX_*``: generous for real hardware, small
enough that a 20-byte edit of a manifest cannot allocate gigabytes), and checks of the numbers,
arrays and declared shapes that come from outside, each refusing a bad value in one line that
names its file (or flag) and field before any work is done.
"""

from __future__ import annotations

import math
import os
import re
from typing import IO, Any

import numpy as np

from psfkit.errors import InvalidInputError

MAX_GRID_SIDE = 64            # positions per side of a *simulated* lattice (--rows, --cols)
MAX_GRID_CELLS = 2**22        # cells a grid's manifest may declare (its grid_shape), a sanity
                              # bound: whether a grid can be analysed is decided from memory
                              # (psfkit.io.grid_validation.analysis_memory_bytes)
MAX_IMAGE_SIDE = 16384        # pixels per image side (a 1440 x 1080 sensor is far below)
#: Smallest PSF frame (pixels per side): what registration needs for a PSF of a few pixels
#: with background around it. Measured: a 3 x 3 grid of Gaussian PSFs (sigma 1.2 px, 1.5 px
#: apart, 5 noise seeds) registers with a largest shift error of 0.25 px on 8 px frames,
#: 0.05 px on 10, 0.01 px on 11 and below 0.005 px from 12 px on (phase correlation refined
#: over +-1.5 px; the noise is estimated from the darkest quarter of every other pixel).
MIN_PSF_SIDE = 12
#: Smallest scene / measurement of an image pair (pixels per side, after --downsample): a
#: forward model of a few kernels needs at least this many pixels to be fitted.
MIN_PAIR_SIDE = 4
MAX_IMAGE_PIXELS = 64 * 2**20  # pixels per channel of one image
MAX_SCENE_PADDING = 8         # convolution grid as a multiple of the sensor size
MAX_ITERATIONS = 10_000       # solver iterations (ADMM, conjugate gradients)
#: Largest sum of |values| of one kernel channel: the most a forward model can multiply a
#: unit scene by. Normal operators (ADMM, least squares) apply it twice, so 1e12 keeps
#: 1e14 of float32's range (3.4e38) for scene values and iterations; a PSF normalised to
#: unit peak over a 4096 x 4096 sensor sums to at most 1.7e7.
MAX_KERNEL_GAIN = 1e12
#: Smallest largest-channel sum of |values| of a kernel file: below it the model predicts an
#: almost black image, and solvers that invert it lose float32's range (ADMM of the tiny
#: bench model stays finite at 1e-18, diverges at 1e-24).
MIN_KERNEL_GAIN = 1e-12
MAX_JSON_DEPTH = 64           # nesting of a JSON document we read
MAX_JSON_BYTES = 16 * 2**20   # size of a JSON document we read (a 64 x 64 manifest: ~1 MB)
MAX_ARRAY_ELEMENTS = 4 * MAX_IMAGE_PIXELS  # elements of one array read from a file
MAX_DOWNSAMPLE = 64           # binning factor
MAX_WHITE_LEVEL = 2.0**32     # the largest value a 32-bit integer file can store
MAX_SEED = 2**32 - 1          # numpy's and torch's seeds agree on [0, 2**32)
MAX_THREADS = 256             # CPU threads (libgomp aborts the process on absurd counts)


def machine_memory_bytes() -> int:
    """Physical memory of this machine in bytes (8 GiB where the system does not say)."""
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return 8 * 2**30
    return int(pages) * int(size) if pages > 0 and size > 0 else 8 * 2**30


def format_bytes(size: float) -> str:
    """``"3.2 GiB"``, ``"512 MiB"``: a byte count for a message."""
    for unit, scale in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if size >= scale:
            return f"{size / scale:.3g} {unit}"
    return f"{int(size)} bytes"


def require_finite(array: Any, what: str) -> np.ndarray:
    """``array`` as a NumPy array; :class:`InvalidInputError` naming ``what`` (a file, a
    flag, ``"FILE: field"``) when it is not numeric or holds NaN/Inf."""
    values = np.asarray(array)
    if values.dtype.kind not in "fcbiu":
        raise InvalidInputError(f"{what}: expected numbers, got {values.dtype} data")
    bad = _count_nonfinite(values)
    if bad:
        raise InvalidInputError(f"{what}: contains {bad} NaN/Inf value(s)")
    return values


def require_finite_output(array: Any, what: str) -> np.ndarray:
    """Refuse to write an array holding NaN/Inf (``what`` names the output file)."""
    values = np.asarray(array)
    bad = _count_nonfinite(values)
    if bad:
        raise InvalidInputError(f"{what}: refusing to write {bad} non-finite value(s) "
                                "(NaN/Inf); an input or a parameter made the result diverge")
    return values


def _count_nonfinite(values: np.ndarray) -> int:
    """NaN/Inf count of a float or complex array; 0 for any other kind (integers are finite)."""
    if values.dtype.kind not in "fc":
        return 0
    return int(np.count_nonzero(~np.isfinite(values)))


def finite_number(value: Any, what: str, minimum: float | None = None,
                  maximum: float | None = None) -> float:
    """``value`` as a finite float in ``[minimum, maximum]``; booleans and strings refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError(f"{what} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise InvalidInputError(f"{what} must be a finite number, got {value!r}")
    if minimum is not None and number < minimum:
        raise InvalidInputError(f"{what} must be >= {minimum:g}, got {value!r}")
    if maximum is not None and number > maximum:
        raise InvalidInputError(f"{what} must be <= {maximum:g}, got {value!r}")
    return number


def exact_int(value: Any, what: str, minimum: int = 0, maximum: int | None = None) -> int:
    """``value`` as an ``int`` (a JSON integer, not ``true`` and not ``2.5``) in range."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InvalidInputError(f"{what} must be an integer, got {value!r}")
    number = int(value)
    if number < minimum:
        raise InvalidInputError(f"{what} must be >= {minimum}, got {number}")
    if maximum is not None and number > maximum:
        raise InvalidInputError(f"{what} {number} exceeds the limit of {maximum}")
    return number


def bounded_size(shape: Any, what: str, max_side: int = MAX_IMAGE_SIDE,
                 max_total: int | None = MAX_IMAGE_PIXELS, unit: str = "pixels") -> tuple[int, ...]:
    """A size (tuple of positive integers) from a file, checked against ``max_side`` per
    axis and ``max_total`` in all before anything is allocated."""
    try:
        sides = tuple(shape)
    except TypeError:
        raise InvalidInputError(f"{what} must be a list of integers, got {shape!r}") from None
    for side in sides:
        if isinstance(side, bool) or not isinstance(side, (int, np.integer)) or side < 1:
            raise InvalidInputError(f"{what} must be positive integers, got {list(sides)!r}")
    sides = tuple(int(s) for s in sides)
    if any(s > max_side for s in sides):
        limit = " x ".join([str(max_side)] * max(len(sides), 1))
        raise InvalidInputError(f"{what} {list(sides)} exceeds the limit of {limit} {unit}")
    if max_total is not None and math.prod(sides) > max_total:
        raise InvalidInputError(f"{what} {list(sides)} exceeds the limit of {max_total} {unit}")
    return sides


def check_array_shape(shape: Any, dtype: Any, what: str,
                      max_elements: int = MAX_ARRAY_ELEMENTS) -> tuple[int, ...]:
    """A shape declared by a file header (``.npy``, ``.npz`` member, TIFF series), refused
    before anything is allocated when an axis exceeds ``MAX_IMAGE_SIDE`` or it holds more than
    ``max_elements`` (the message gives the bytes of ``dtype``)."""
    sides = tuple(int(s) for s in shape)
    total = math.prod(sides)
    if any(s > MAX_IMAGE_SIDE for s in sides) or total > max_elements:
        size = total * (np.dtype(dtype).itemsize if dtype is not None else 1)
        raise InvalidInputError(f"{what} declares shape {list(sides)} ({total} elements, "
                                f"{size / 1e9:.3g} GB); the limit is {MAX_IMAGE_SIDE} per axis "
                                f"and {max_elements} elements")
    return sides


def npy_header(stream: IO[bytes], what: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    """``(shape, fortran_order, dtype)`` from the header of an ``.npy`` stream (a file or an
    ``.npz`` member: only the header is decompressed); refused when it is not one."""
    try:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            return np.lib.format.read_array_header_1_0(stream)
        return np.lib.format.read_array_header_2_0(stream)
    except ValueError as exc:   # numpy's message for a bad magic string or header
        reason = str(exc).splitlines()[0] if str(exc) else "bad header"
        raise InvalidInputError(f"{what}: not a readable .npy array ({reason[:120]})") from None


def escape_line(text: str) -> str:
    """``text`` with its control characters written as escapes (``\\n``, ``\\x1b``...), so
    that a file name holding a newline cannot split a one-line message or colour a terminal."""
    return re.sub(r"[\x00-\x1f\x7f\x85\u2028\u2029]",
                  lambda m: repr(m.group())[1:-1], text)
