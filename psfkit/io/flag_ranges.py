"""The type and range of every numeric flag, declared once (:data:`FLAGS`): :func:`flag`
gives the ``argparse`` type, :meth:`FlagRange.check` checks a value read from a file; ``ekdun``
passes its own table."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from psfkit.errors import InvalidInputError
from psfkit.io.validation import (
    MAX_DOWNSAMPLE,
    MAX_GRID_SIDE,
    MAX_ITERATIONS,
    MAX_SEED,
    MAX_THREADS,
    escape_line,
    exact_int,
    finite_number,
)


@dataclass(frozen=True)
class FlagRange:
    """The type (``int`` or ``float``) and range of one numeric flag: ``low``/``high`` are
    inclusive bounds (``None``: none), exclusive with ``low_open``/``high_open``."""

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

#: Every numeric flag of ``psfkit`` with its range, declared once. A key ``"COMMAND --flag"``
#: overrides ``"--flag"`` for that command. ``tests/e2e/test_bad_inputs.py`` checks that no
#: numeric flag of the parser escapes this table.
FLAGS: dict[str, FlagRange] = {
    "--seed": FlagRange(int, 0, MAX_SEED),
    "--threads": FlagRange(int, 1, MAX_THREADS),
    "--downsample": FlagRange(int, 1, MAX_DOWNSAMPLE),
    "--iterations": _ITERATIONS,
    # preprocessing, characterization, fits
    "--saturation-level": FlagRange(float, 0, 1e12, low_open=True),
    "--hot-pixel-sigma": FlagRange(float, 0, 1e6, low_open=True),
    "--upsample": FlagRange(int, 1, 1000),
    "--mae-smoothing": _SIGMA_PX,
    "--folds": FlagRange(int, 2, MAX_GRID_SIDE ** 2),
    "--min-ncc": FlagRange(float, 0, 1),
    "--tikhonov": _WEIGHT,
    "--difference": _WEIGHT,
    "--support-threshold": FlagRange(float, 0, 1, high_open=True),
    "--projected-iterations": _ITERATIONS,
    # the virtual bench (BenchConfig checks the same ranges for --bench-config files)
    "--rows": _SIDE,
    "--cols": _SIDE,
    "--extent": FlagRange(float, 0, 1, low_open=True),
    "--diffusion-angle": FlagRange(float, 0, 20, low_open=True),
    "--gap-mm": FlagRange(float, 0, 1000, low_open=True),
    "--peak-fraction": FlagRange(float, 0, 100, low_open=True),
    "--frames": FlagRange(int, 1, 10_000),
}


def flag_range(name: str, command: str | None = None,
               table: Mapping[str, FlagRange] = FLAGS) -> FlagRange:
    """The ``table`` entry of ``name`` (``"COMMAND NAME"`` first; default :data:`FLAGS`)."""
    return table.get(f"{command} {name}") or table[name]


def flag(name: str, command: str | None = None,
         table: Mapping[str, FlagRange] = FLAGS) -> Callable[[str], int | float]:
    """``argparse`` type of the numeric flag ``name`` (range from ``table``); it carries
    ``flag_range`` so that tests can check the parsers against the table."""
    spec = flag_range(name, command, table)

    def parse(text: str) -> int | float:
        return spec.parse(text)

    parse.__name__ = spec.kind.__name__   # argparse's "invalid int value" wording
    parse.flag_range = spec               # type: ignore[attr-defined]
    return parse
