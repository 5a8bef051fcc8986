"""Exceptions raised by the toolkit: a one-line message naming the input (file, argument)
and the problem, which the command-line interfaces print before exiting non-zero."""

from __future__ import annotations


class PsfkitError(Exception):
    """Base class of all errors raised on purpose by ``psfkit`` and ``ekdun``."""


class InvalidInputError(PsfkitError):
    """An input file, folder or array is missing, malformed or physically implausible."""


class GridFormatError(InvalidInputError):
    """A PSF-grid folder or its manifest does not follow the grid format."""


class PositionRejected(InvalidInputError):
    """One PSF of a grid fails a quality check (``reason``: one of
    :data:`psfkit.calibration.alignment.REJECTION_REASONS`); the analyses exclude it."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


class ModelFileError(InvalidInputError):
    """A kernel or model file is of the wrong format, version or shape."""


class ConfigurationError(PsfkitError):
    """A parameter value (from the API or the command line) is out of range or inconsistent."""
