"""Exceptions raised by the toolkit.

Every library function that rejects its input raises a subclass of :class:`PsfkitError`
whose message names the offending input (file, argument) and the problem, in one line.
The command-line interfaces print that line and exit with a non-zero status.
"""

from __future__ import annotations


class PsfkitError(Exception):
    """Base class of all errors raised on purpose by ``psfkit`` and ``ekdun``."""


class InvalidInputError(PsfkitError):
    """An input file, folder or array is missing, malformed or physically implausible."""


class GridFormatError(InvalidInputError):
    """A PSF-grid folder or its manifest does not follow the grid format."""


class PositionRejected(InvalidInputError):
    """One PSF of a grid fails a quality check (``reason``: one of
    :data:`psfkit.calibration.alignment.REJECTION_REASONS`). The grid analyses exclude that
    position and carry on (unless ``strict``, or it is the reference PSF)."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


class ModelFileError(InvalidInputError):
    """A kernel or model file is of the wrong format, version or shape."""


class ConfigurationError(PsfkitError):
    """A parameter value (from the API or the command line) is out of range or inconsistent."""
