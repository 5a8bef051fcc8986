"""The PSF-grid folder format: a folder of point-source images plus a manifest.

A grid is what a lab hands over after displaying a point at N × M field positions and
capturing the camera's response at each. The format is documented in ``docs/grid-format.md``;
in short::

    grid/
      manifest.json            (or manifest.csv)
      psf_r00_c00.tiff ...     one image per grid position: 16-bit TIFF/PNG or .npy, mono or RGB
      dark.tiff                optional dark / black frame, same shape and type

This module holds the grid's data classes (:class:`GridPosition`, :class:`PsfGrid`).
:func:`psfkit.io.grid_validation.read_grid` validates the whole folder before anything is
computed and raises :class:`~psfkit.errors.GridFormatError` naming the file and the problem
(the manifest is parsed by :mod:`psfkit.io.manifest`); :class:`psfkit.io.grid_writer.GridWriter`
writes a grid atomically (into a temporary folder renamed into place when complete). All three
are importable from :mod:`psfkit.io`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import GridFormatError, InvalidInputError
from psfkit.io.images import read_image
from psfkit.validation import require_finite

FORMAT_NAME = "psfkit-grid"
FORMAT_VERSION = 1
MANIFEST_JSON = "manifest.json"
MANIFEST_CSV = "manifest.csv"


@dataclass(frozen=True)
class GridPosition:
    """One point-source position of a grid.

    Attributes
    ----------
    file : str
        Image file name, relative to the grid folder.
    row, col : int
        Grid index; ``row`` grows with the field's ``y`` (down), ``col`` with its ``x`` (right).
    monitor_px : (float, float) or None
        Source position ``(x, y)`` on the monitor in monitor pixels, relative to the point on
        the camera's optical axis, in the displayed image's frame (x right, y down).
    field_deg : (float, float) or None
        Field angles ``(θx, θy)`` in degrees, ``tan θx = x / z`` for a source at lateral
        position ``(x, y)`` and distance ``z``. A source at ``+x`` moves the PSF towards ``-u``.
    exposure_s : float or None
        Exposure time in seconds (images are divided by it when exposures differ).
    """

    file: str
    row: int
    col: int
    monitor_px: tuple[float, float] | None = None
    field_deg: tuple[float, float] | None = None
    exposure_s: float | None = None


@dataclass(frozen=True)
class PsfGrid:
    """A validated PSF grid on disk; images are read on demand (one at a time).

    Use :func:`read_grid` to create one. Images are returned as ``(C, H, W)`` float32 in the
    stored units (no dark subtraction; see :mod:`psfkit.preprocess` for that).
    """

    root: Path
    positions: tuple[GridPosition, ...]
    grid_shape: tuple[int, int]
    image_shape: tuple[int, int, int]
    dtype: np.dtype
    channels: tuple[str, ...]
    channel_order: str = "RGB"
    dark_file: str | None = None
    black_level: float | None = None
    bit_depth: int | None = None
    pixel_pitch_um: float | None = None
    center_index: tuple[int, int] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def manifest_name(self) -> str:
        return self.metadata.get("_manifest", MANIFEST_JSON)

    def position(self, row: int, col: int) -> GridPosition:
        """The :class:`GridPosition` at grid index ``(row, col)``."""
        n_rows, n_cols = self.grid_shape
        if not (0 <= row < n_rows and 0 <= col < n_cols):
            raise InvalidInputError(
                f"{self.root}: grid index ({row}, {col}) outside the {n_rows}×{n_cols} grid")
        return self.positions[row * n_cols + col]

    def path(self, row: int, col: int) -> Path:
        return self.root / self.position(row, col).file

    def load(self, row: int, col: int) -> np.ndarray:
        """Image at ``(row, col)`` as ``(C, H, W)`` float32, stored units."""
        return read_image(self.path(row, col), self.channel_order, dtype=np.float32)

    def load_dark(self) -> np.ndarray | None:
        """The dark frame as ``(C, H, W)`` float32, or ``None`` when the grid has none."""
        if self.dark_file is None:
            return None
        path = self.root / self.dark_file
        return checked_dark(path, read_image(path, self.channel_order)).astype(np.float32)

    def field_deg(self) -> np.ndarray | None:
        """Field angles as an ``(N, M, 2)`` array of ``(θx, θy)`` degrees, or ``None``."""
        if any(p.field_deg is None for p in self.positions):
            return None
        return np.array([p.field_deg for p in self.positions], dtype=np.float64).reshape(
            *self.grid_shape, 2)

    def monitor_px(self) -> np.ndarray | None:
        """Monitor positions as an ``(N, M, 2)`` array of ``(x, y)``, or ``None``."""
        if any(p.monitor_px is None for p in self.positions):
            return None
        return np.array([p.monitor_px for p in self.positions], dtype=np.float64).reshape(
            *self.grid_shape, 2)

    def exposures(self) -> np.ndarray | None:
        """Exposure times as an ``(N, M)`` array, or ``None`` when any is missing."""
        if any(p.exposure_s is None for p in self.positions):
            return None
        return np.array([p.exposure_s for p in self.positions], dtype=np.float64).reshape(
            self.grid_shape)

    def require_center(self) -> tuple[int, int]:
        """Grid index of the on-axis (reference) PSF; raises when the grid has none."""
        if self.center_index is None:
            n_rows, n_cols = self.grid_shape
            raise GridFormatError(
                f"{self.root / self.manifest_name}: the {n_rows}×{n_cols} grid has no centre "
                "position (no position at field (0, 0) and no odd-sized middle); add "
                "\"center\": [row, col] to the manifest")
        return self.center_index


def checked_dark(path: Path, image: np.ndarray) -> np.ndarray:
    """The dark frame, refused when it holds NaN/Inf (one check for every command)."""
    try:
        return require_finite(image, f"{path}: dark frame")
    except InvalidInputError as exc:
        raise GridFormatError(str(exc)) from None
