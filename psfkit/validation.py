"""Validation at the boundaries: numbers, sizes and JSON documents that come from outside.

Every value read from a file or the command line passes one of these functions where it enters,
so a bad value is refused with one line that names its file (or flag) and field before any
work is done, and a non-finite result can never be written:

- :func:`require_finite` / :func:`finite_number` / :func:`bounded_size` / :func:`exact_int`:
  arrays and scalars from files, checked finite and in range;
- :func:`load_json_document`: strict JSON (duplicate keys, NaN/Infinity literals and absurd
  nesting refused) that names the file;
- :func:`dumps_finite`: JSON for outputs, refusing NaN/Inf instead of writing bare ``NaN``;
- :func:`finite_float`, :func:`positive_float`, :func:`nonnegative_float`, :func:`fraction`,
  :func:`positive_int`: ``argparse`` types for command-line numbers.

The limits (``MAX_*``) are generous for real hardware and small enough that a 20-byte edit
of a manifest cannot make a command allocate gigabytes.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from psfkit.errors import InvalidInputError

MAX_GRID_SIDE = 64            # grid positions per side (the paper's grids are 9 x 9)
MAX_IMAGE_SIDE = 16384        # pixels per image side (a 1440 x 1080 sensor is far below)
MAX_IMAGE_PIXELS = 64 * 2**20  # pixels per channel of one image
MAX_SCENE_PADDING = 8         # convolution grid as a multiple of the sensor size
MAX_ITERATIONS = 10_000       # solver iterations (ADMM, conjugate gradients)
MAX_UNROLLED_ITERATIONS = 100  # unrolled iterations of a network (the paper uses 10)
MAX_JSON_DEPTH = 64           # nesting of a JSON document we read


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


# --------------------------------------------------------------------------- argparse types


def _parse_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """``argparse`` type: a finite float (``nan``, ``inf`` refused)."""
    return _parse_float(text)


def positive_float(text: str) -> float:
    """``argparse`` type: a finite float > 0."""
    value = _parse_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """``argparse`` type: a finite float >= 0."""
    value = _parse_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def fraction(text: str) -> float:
    """``argparse`` type: a finite float in ``[0, 1]``."""
    value = _parse_float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text!r}")
    return value


def positive_int(text: str) -> int:
    """``argparse`` type: an integer >= 1 (at most ``MAX_ITERATIONS`` × 100, a sanity bound)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    if value > 100 * MAX_ITERATIONS:
        raise argparse.ArgumentTypeError(f"{value} exceeds the limit of {100 * MAX_ITERATIONS}")
    return value


class OneLineArgumentParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line on stderr (exit status 2), like
    every other error of the command-line interfaces; ``--help`` still shows the usage."""

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.split()[0]   # "psfkit: error: ..." like every other error
        sys.stderr.write(f"{command}: error: {message} (see {self.prog} --help)\n")
        sys.exit(2)
