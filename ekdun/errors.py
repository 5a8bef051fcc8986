"""Exceptions raised by ekdun: subclasses of :mod:`psfkit.errors`, so the CLIs print them as
one line.
"""

from __future__ import annotations

from psfkit.errors import ConfigurationError, InvalidInputError

__all__ = ["CheckpointError", "ConfigurationError", "InvalidInputError", "KernelShapeError",
           "TensorShapeError"]


class TensorShapeError(InvalidInputError):
    """A scene or measurement tensor has the wrong rank, size, channel count or dtype."""


class KernelShapeError(InvalidInputError):
    """Kernels or weight maps are malformed (wrong rank, larger than the sensor, ...)."""


class CheckpointError(InvalidInputError):
    """A checkpoint file is missing, corrupt, foreign or unsafe, or cannot rebuild its network."""
