"""The type and range of every numeric flag of ``ekdun``, declared once, and ``--device``.

:data:`FLAGS` extends :data:`psfkit.io.flag_ranges.FLAGS` with ekdun's own (a key
``"COMMAND --flag"`` overrides ``"--flag"`` for that command); ``tests/e2e/test_bad_inputs.py``
checks that no numeric flag escapes it.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable

from psfkit.io import flag_ranges as shared
from psfkit.io.flag_ranges import FlagRange
from psfkit.io.validation import MAX_GRID_SIDE, MAX_THREADS, escape_line

MAX_UNROLLED_ITERATIONS = 100  # unrolled iterations of a network (the paper uses 10)

_POSITIVE_COUNT = FlagRange(int, 1, 1_000_000)
_WEIGHT = FlagRange(float, 0, 1e6)

FLAGS: dict[str, FlagRange] = {
    **shared.FLAGS,
    "--loader-workers": FlagRange(int, 1, MAX_THREADS),
    # the virtual-bench dataset
    "--sensor": FlagRange(int, 16, 4096),
    "--grid": FlagRange(int, 1, MAX_GRID_SIDE),
    "--n-train": _POSITIVE_COUNT,
    "--n-test": _POSITIVE_COUNT,
    "--oracle-scenes": FlagRange(int, 0, 1_000_000),
    "--half-fov": FlagRange(float, 0, 80, low_open=True),
    "--aperture": FlagRange(float, 0, 100, low_open=True),
    # below one photo-electron per unit measurement a white pixel holds less than one
    # electron: noise only (and at 1e-300 the read noise / photons overflows float32)
    "--photons": FlagRange(float, 1, 1e12),
    "--grid-frames": FlagRange(int, 1, 10_000),
    # training
    "train --iterations": FlagRange(int, 1, MAX_UNROLLED_ITERATIONS),
    "--epochs": FlagRange(int, 1, 100_000),
    "--batch-size": FlagRange(int, 1, 65_536),
    "--lr": FlagRange(float, 0, 1, low_open=True),
    "--kernel-lr-scale": FlagRange(float, 0, 1e6),
    # classical reconstruction
    "--tv": _WEIGHT,
    "--tol": FlagRange(float, 0, 1),
}


def flag_range(name: str, command: str | None = None) -> FlagRange:
    """The :data:`FLAGS` entry of ``name`` (``"COMMAND NAME"`` first)."""
    return shared.flag_range(name, command, FLAGS)


def flag(name: str, command: str | None = None) -> Callable[[str], int | float]:
    """``argparse`` type of ekdun's numeric flag ``name`` (its range from :data:`FLAGS`)."""
    return shared.flag(name, command, FLAGS)


DEVICE_PATTERN = re.compile(r"(auto|cpu|mps|cuda(:[0-9]{1,3})?)")


def device_name(text: str) -> str:
    """``argparse`` type of ``--device``: ``auto``, ``cpu``, ``cuda``, ``cuda:N`` or ``mps``
    (whether that device exists is checked when it is used)."""
    if not DEVICE_PATTERN.fullmatch(text):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda, cuda:N or mps, got "
                                         f"{escape_line(repr(text))}")
    return text
