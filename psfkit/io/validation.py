"""Validation at the boundaries: numbers, sizes and JSON documents that come from outside.

Every value read from a file or the command line passes one of these functions where it enters,
so a bad value is refused with one line that names its file (or flag) and field before any
work is done, and a non-finite result can never be written:

- :func:`require_finite` / :func:`finite_number` / :func:`bounded_size` / :func:`exact_int`:
  arrays and scalars from files, checked finite and in range;
- :func:`load_json_document`: strict JSON (duplicate keys, NaN/Infinity literals and absurd
  nesting refused) that names the file;
- :func:`dumps_finite`: JSON for outputs, refusing NaN/Inf instead of writing bare ``NaN``;
- :func:`read_json_file`: :func:`load_json_document` of a file whose size is checked first;
- :func:`npy_header` / :func:`check_array_shape`: the shape an ``.npy`` file (or an ``.npz``
  member) declares, read and checked before a byte of its data is read or decompressed;
- :data:`FLAGS` and :func:`flag`: the one table of every numeric flag of both command-line
  interfaces (``psfkit`` and ``ekdun``) with its range; :func:`flag` gives the ``argparse``
  type, :meth:`FlagRange.check` the same range for the same value read from a file;
- :func:`device_name`: ``argparse`` type of ``--device``;
- :func:`escape_line`: control characters (a newline in a file name) made visible, so that
  an error stays one line.

The limits (``MAX_*``) are generous for real hardware and small enough that a 20-byte edit
of a manifest cannot make a command allocate gigabytes.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
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
MAX_UNROLLED_ITERATIONS = 100  # unrolled iterations of a network (the paper uses 10)
MAX_JSON_DEPTH = 64           # nesting of a JSON document we read
MAX_JSON_BYTES = 16 * 2**20   # size of a JSON document we read (a 64 x 64 manifest: ~1 MB)
MAX_ARRAY_ELEMENTS = 4 * MAX_IMAGE_PIXELS  # elements of one array read from a file
MAX_DOWNSAMPLE = 64           # binning factor
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
    """Return ``array`` as a NumPy array; raise when it holds NaN or ±Inf.

    Parameters
    ----------
    array : array-like
        Any numeric array (integer arrays are always finite).
    what : str
        Names the input in the message (a file, a flag, ``"FILE: field"``).

    Raises
    ------
    InvalidInputError
        ``"{what}: contains N NaN/Inf value(s)"``.
    """
    values = np.asarray(array)
    if values.dtype.kind in "fc":
        bad = int(np.count_nonzero(~np.isfinite(values)))
        if bad:
            raise InvalidInputError(f"{what}: contains {bad} NaN/Inf value(s)")
    elif values.dtype.kind not in "biu":
        raise InvalidInputError(f"{what}: expected numbers, got {values.dtype} data")
    return values


def require_finite_output(array: Any, what: str) -> np.ndarray:
    """Refuse to write an array holding NaN/Inf (``what`` names the output file).

    Raises
    ------
    InvalidInputError
        ``"{what}: refusing to write N non-finite value(s) (NaN/Inf); ..."``.
    """
    values = np.asarray(array)
    if values.dtype.kind in "fc":
        bad = int(np.count_nonzero(~np.isfinite(values)))
        if bad:
            raise InvalidInputError(f"{what}: refusing to write {bad} non-finite value(s) "
                                    "(NaN/Inf); an input or a parameter made the result diverge")
    return values


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
    """A size (tuple of positive integers) from a file, refused before anything is allocated.

    Raises
    ------
    InvalidInputError
        ``"{what} [100000, 100000] exceeds the limit of 64 x 64 positions"`` and the like.
    """
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
    """Every axis of a declared array shape and its total size, before anything is allocated.

    Parameters
    ----------
    shape : sequence of int
        As declared by a file header (``.npy``, ``.npz`` member, TIFF series).
    dtype : numpy dtype or None
        Its element type (the message gives the bytes it would take).
    what : str
        Names the file (or ``"FILE: member"``) in the message.
    max_elements : int
        At most this many elements in all (every axis also at most ``MAX_IMAGE_SIDE``).

    Raises
    ------
    InvalidInputError
        ``"{what} declares shape [...] (N elements, X GB); the limit is ..."``.
    """
    sides = tuple(int(s) for s in shape)
    total = math.prod(sides)
    if any(s > MAX_IMAGE_SIDE for s in sides) or total > max_elements:
        size = total * (np.dtype(dtype).itemsize if dtype is not None else 1)
        raise InvalidInputError(f"{what} declares shape {list(sides)} ({total} elements, "
                                f"{size / 1e9:.3g} GB); the limit is {MAX_IMAGE_SIDE} per axis "
                                f"and {max_elements} elements")
    return sides


def npy_header(stream: IO[bytes], what: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    """``(shape, fortran_order, dtype)`` from the header of an ``.npy`` stream (a file, or an
    ``.npz`` member opened with :mod:`zipfile`: only the header bytes are decompressed).

    Raises
    ------
    InvalidInputError
        Not an ``.npy`` header (``what`` names the file).
    """
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


# --------------------------------------------------------------------------- JSON


def _refuse_duplicates(where: str):
    def hook(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        doc: dict[str, Any] = {}
        for key, value in pairs:
            if key in doc:
                raise InvalidInputError(f"{where}: key {key!r} appears twice")
            doc[key] = value
        return doc
    return hook


def _refuse_constant(where: str):
    def hook(name: str) -> float:
        raise InvalidInputError(f"{where}: {name} is not a valid JSON number")
    return hook


def _nesting_depth(text: str) -> int:
    """Deepest bracket nesting outside strings (cheap, linear, no recursion)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _refuse_overflow(where: str):
    def hook(text: str) -> float:
        value = float(text)
        if not math.isfinite(value):
            raise InvalidInputError(f"{where}: number {text} is out of range")
        return value
    return hook


def load_json_document(text: str | bytes, where: str) -> Any:
    """Parse JSON from a file we were given, strictly.

    Duplicate keys, ``NaN``/``Infinity`` literals, numbers that overflow to infinity
    (``1e400``) and nesting deeper than ``MAX_JSON_DEPTH``
    (which would exhaust the parser's recursion) are refused; errors name ``where``.

    Raises
    ------
    InvalidInputError
    """
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise InvalidInputError(f"{where}: not a UTF-8 text file") from None
    if _nesting_depth(text) > MAX_JSON_DEPTH:
        raise InvalidInputError(f"{where}: JSON nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        return json.loads(text, object_pairs_hook=_refuse_duplicates(where),
                          parse_constant=_refuse_constant(where),
                          parse_float=_refuse_overflow(where))
    except json.JSONDecodeError as exc:
        raise InvalidInputError(f"{where}: invalid JSON at line {exc.lineno}: {exc.msg}") \
            from None
    except RecursionError:
        raise InvalidInputError(f"{where}: JSON nested too deeply") from None


def read_json_file(path: str | os.PathLike, where: str | None = None,
                   max_bytes: int = MAX_JSON_BYTES) -> Any:
    """:func:`load_json_document` of a file, its size checked before it is read (a sparse
    1 GB ``manifest.json`` is refused from its size, not read).

    Raises
    ------
    InvalidInputError
        Missing, larger than ``max_bytes``, or not valid JSON; ``where`` (default: the path)
        names it.
    """
    path = Path(path)
    where = where or str(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InvalidInputError(f"{where}: no such file") from None
    if size > max_bytes:
        raise InvalidInputError(f"{where}: {size} bytes is larger than the {max_bytes} bytes a "
                                "JSON document of this toolkit may have")
    with open(path, "rb") as fh:
        return load_json_document(fh.read(max_bytes + 1), where)


def dumps_finite(doc: Any, what: str, **kwargs: Any) -> str:
    """``json.dumps(doc, allow_nan=False)``: a NaN/Inf in an output is an error naming it.

    Parameters
    ----------
    doc : JSON-able object
    what : str
        The output (file name) for the message.
    **kwargs
        Passed to :func:`json.dumps` (``indent``, ``default``...).

    Raises
    ------
    InvalidInputError
        ``"{what}: refusing to write a non-finite number (NaN/Inf) at KEY"``.
    """
    try:
        return json.dumps(doc, allow_nan=False, **kwargs)
    except ValueError:
        pass
    where = _first_non_finite(doc, kwargs.get("default"))
    raise InvalidInputError(f"{what}: refusing to write a non-finite number (NaN/Inf)"
                            + (f" at {where}" if where else "")
                            + "; an input or a parameter made the result diverge")


def _first_non_finite(value: Any, default: Any, path: str = "") -> str | None:
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        if not isinstance(value, (int, float, str, bool, type(None))) and default is not None:
            try:
                value = default(value)
            except Exception:
                return None
        if isinstance(value, float) and not math.isfinite(value):
            return path or "top level"
        return None
    for key, item in items:
        found = _first_non_finite(item, default, f"{path}.{key}" if path else str(key))
        if found:
            return found
    return None


# --------------------------------------------------------------------------- the flag table


@dataclass(frozen=True)
class FlagRange:
    """The type and range of one numeric flag.

    ``kind`` is ``int`` or ``float``; ``low``/``high`` are inclusive bounds (``None``: none),
    except that ``low`` is excluded when ``low_open`` (``> 0`` rather than ``>= 0``), and
    ``high`` when ``high_open``.
    """

    kind: type
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def describe(self) -> str:
        """``"an integer in [1, 64]"``, ``"a number in (0, 1]"``..."""
        noun = "an integer" if self.kind is int else "a number"
        low = "-inf" if self.low is None else _number_text(self.low)
        high = "inf" if self.high is None else _number_text(self.high)
        return (f"{noun} in {'(' if self.low_open or self.low is None else '['}{low}, {high}"
                f"{')' if self.high_open or self.high is None else ']'}")

    def _in_range(self, value: float) -> bool:
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open
                                     else value <= self.high)

    def parse(self, text: str) -> int | float:
        """The ``argparse`` conversion: a finite number of the right kind, in range."""
        try:
            value: int | float = int(text) if self.kind is int else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {self.describe()}, got "
                                             f"{escape_line(repr(text))}") from None
        if not math.isfinite(value) or not self._in_range(value):
            raise argparse.ArgumentTypeError(f"must be {self.describe()}, got "
                                             f"{escape_line(text)}")
        return value

    def check(self, value: Any, what: str) -> int | float:
        """The same range for a value read from a file (``what`` names the file and field)."""
        if self.kind is int:
            return exact_int(value, what, -2**63 if self.low is None else int(self.low)
                             + int(self.low_open),
                             None if self.high is None else int(self.high))
        number = finite_number(value, what)
        if not self._in_range(number):
            raise InvalidInputError(f"{what} must be {self.describe()}, got {value!r}")
        return number


def _number_text(value: float) -> str:
    return str(int(value)) if float(value).is_integer() and abs(value) < 1e10 else f"{value:g}"


_ITERATIONS = FlagRange(int, 1, MAX_ITERATIONS)
_POSITIVE_COUNT = FlagRange(int, 1, 1_000_000)
_SIDE = FlagRange(int, 1, MAX_GRID_SIDE)
_WEIGHT = FlagRange(float, 0, 1e6)
_SIGMA_PX = FlagRange(float, 0, 64)

#: Every numeric flag of ``psfkit`` and ``ekdun`` with its range, declared once. A key
#: ``"COMMAND --flag"`` overrides ``"--flag"`` for that command. ``tests/e2e/test_bad_inputs.py``
#: checks that no numeric flag of either parser escapes this table.
FLAGS: dict[str, FlagRange] = {
    # shared
    "--seed": FlagRange(int, 0, MAX_SEED),
    "--threads": FlagRange(int, 1, MAX_THREADS),
    "--loader-workers": FlagRange(int, 1, MAX_THREADS),
    "--downsample": FlagRange(int, 1, MAX_DOWNSAMPLE),
    "--iterations": _ITERATIONS,
    # psfkit: preprocessing, characterization, fits
    "--saturation-level": FlagRange(float, 0, 1e12, low_open=True),
    "--hot-pixel-sigma": FlagRange(float, 0, 1e6, low_open=True),
    "--upsample": FlagRange(int, 1, 1000),
    "--mae-smoothing": _SIGMA_PX,
    "--smooth": _SIGMA_PX,
    "--folds": FlagRange(int, 2, MAX_GRID_SIDE ** 2),
    "--min-ncc": FlagRange(float, 0, 1),
    "--tikhonov": _WEIGHT,
    "--difference": _WEIGHT,
    "--support-threshold": FlagRange(float, 0, 1, high_open=True),
    "--projected-iterations": _ITERATIONS,
    # psfkit: the virtual bench (BenchConfig checks the same ranges for --bench-config files)
    "--rows": _SIDE,
    "--cols": _SIDE,
    "--extent": FlagRange(float, 0, 1, low_open=True),
    "--diffusion-angle": FlagRange(float, 0, 20, low_open=True),
    "--gap-mm": FlagRange(float, 0, 1000, low_open=True),
    "--peak-fraction": FlagRange(float, 0, 100, low_open=True),
    "--frames": FlagRange(int, 1, 10_000),
    # ekdun
    "--sensor": FlagRange(int, 16, 4096),
    "--grid": _SIDE,
    "--n-train": _POSITIVE_COUNT,
    "--n-test": _POSITIVE_COUNT,
    "--oracle-scenes": FlagRange(int, 0, 1_000_000),
    "--half-fov": FlagRange(float, 0, 80, low_open=True),
    "--aperture": FlagRange(float, 0, 100, low_open=True),
    # below one photo-electron per unit measurement a white pixel holds less than one
    # electron: noise only (and at 1e-300 the read noise / photons overflows float32)
    "--photons": FlagRange(float, 1, 1e12),
    "--grid-frames": FlagRange(int, 1, 10_000),
    "train --iterations": FlagRange(int, 1, MAX_UNROLLED_ITERATIONS),
    "--epochs": FlagRange(int, 1, 100_000),
    "--batch-size": FlagRange(int, 1, 65_536),
    "--lr": FlagRange(float, 0, 1, low_open=True),
    "--physics-weight": _WEIGHT,
    "--kernel-lr-scale": FlagRange(float, 0, 1e6),
    "--tv": _WEIGHT,
    "--tol": FlagRange(float, 0, 1),
}


def flag_range(name: str, command: str | None = None) -> FlagRange:
    """The :data:`FLAGS` entry of ``name`` (``"COMMAND NAME"`` first)."""
    return FLAGS.get(f"{command} {name}") or FLAGS[name]


def flag(name: str, command: str | None = None) -> Callable[[str], int | float]:
    """``argparse`` type of the numeric flag ``name`` (its range from :data:`FLAGS`).

    The returned function carries ``flag_range`` so that the parsers can be checked against
    the table.
    """
    spec = flag_range(name, command)

    def parse(text: str) -> int | float:
        return spec.parse(text)

    parse.__name__ = spec.kind.__name__   # argparse's "invalid int value" wording
    parse.flag_range = spec               # type: ignore[attr-defined]
    return parse


DEVICE_PATTERN = re.compile(r"(auto|cpu|mps|cuda(:[0-9]{1,3})?)")


def device_name(text: str) -> str:
    """``argparse`` type of ``--device``: ``auto``, ``cpu``, ``cuda``, ``cuda:N`` or ``mps``
    (whether that device exists is checked when it is used)."""
    if not DEVICE_PATTERN.fullmatch(text):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda, cuda:N or mps, got "
                                         f"{escape_line(repr(text))}")
    return text


class OneLineArgumentParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line on stderr (exit status 2), like
    every other error of the command-line interfaces; ``--help`` still shows the usage."""

    def _get_value(self, action: argparse.Action, arg_string: str) -> Any:
        # Every free-text argument of both CLIs is a path or a name: an empty one (``--out ''``)
        # would read as "not given" (``if args.out``) or as the current folder (``Path('')``),
        # so it is a bad argument, refused here for every argument of every command.
        if arg_string == "" and action.type is None and not action.choices:
            raise argparse.ArgumentError(action, "must not be empty")
        return super()._get_value(action, arg_string)

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.split()[0]   # "psfkit: error: ..." like every other error
        sys.stderr.write(escape_line(f"{command}: error: {message} (see {self.prog} --help)")
                         + "\n")
        sys.exit(2)
