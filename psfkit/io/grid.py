"""The PSF-grid format (``docs/grid-format.md``): a folder of point-source images (16-bit
TIFF/PNG or ``.npy``, one per field position) plus ``manifest.json``/``.csv`` and an optional
dark frame.

Layouts: a full lattice, an incomplete lattice (gaps in the declared ``grid_shape``) and an
irregular scan (positions by field or monitor coordinates only), held as a ``1 × P`` row.
This module holds the data classes; :func:`psfkit.io.grid_validation.read_grid` validates a
folder and :class:`psfkit.io.grid_writer.GridWriter` writes one atomically.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import GridFormatError, InvalidInputError
from psfkit.io.images import read_image
from psfkit.io.validation import require_finite

FORMAT_NAME = "psfkit-grid"
FORMAT_VERSION = 1
MANIFEST_JSON = "manifest.json"
MANIFEST_CSV = "manifest.csv"
FULL_LATTICE = "full lattice"
INCOMPLETE_LATTICE = "incomplete lattice"
IRREGULAR = "irregular"


@dataclass(frozen=True)
class GridPosition:
    """One point-source position of a grid.

    Attributes
    ----------
    file : str
        Image file name, relative to the grid folder.
    row, col : int
        Grid index; ``row`` grows with the field's ``y`` (down), ``col`` with its ``x`` (right).
        An irregular scan: row 0, column = place in the manifest.
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
    """A validated PSF grid on disk (from :func:`read_grid`); images are read on demand as
    ``(C, H, W)`` float32 in stored units (no dark subtraction).

    ``positions``: the captured ones, sorted by index; ``grid_shape``: the declared lattice
    (``(1, P)`` for an irregular scan). Per-position arrays are ``(N, M, ...)``, NaN where not
    captured.
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
    layout: str = FULL_LATTICE

    @cached_property
    def _by_index(self) -> dict[tuple[int, int], GridPosition]:
        return {(p.row, p.col): p for p in self.positions}

    @property
    def frame_problems(self) -> dict[str, str]:
        """File → problem of the PSF frames :func:`read_grid` found unusable (NaN/Inf, all
        zero) without ``strict``."""
        return dict(self.metadata.get("_frame_problems", {}))

    @property
    def is_irregular(self) -> bool:
        return self.layout == IRREGULAR

    def has(self, row: int, col: int) -> bool:
        """Whether grid index ``(row, col)`` was captured."""
        return (row, col) in self._by_index

    def missing(self) -> list[tuple[int, int]]:
        """The cells of the declared lattice that were not captured (row-major)."""
        n_rows, n_cols = self.grid_shape
        return [(r, c) for r in range(n_rows) for c in range(n_cols) if not self.has(r, c)]

    def describe_index(self, index: tuple[int, int]) -> str:
        """``(row, col)`` of a lattice, or ``#i (file)`` of an irregular scan."""
        if self.is_irregular:
            pos = self._by_index.get(index)
            return f"#{index[1]}" + (f" ({pos.file})" if pos is not None else "")
        return f"({index[0]}, {index[1]})"

    def _lattice(self, attr: str, extra: tuple[int, ...]) -> np.ndarray | None:
        """The positions' ``attr`` as an ``(N, M, *extra)`` array (NaN where not captured), or
        ``None`` when any position lacks it."""
        values = [getattr(p, attr) for p in self.positions]
        if any(v is None for v in values):
            return None
        out = np.full((*self.grid_shape, *extra), np.nan)
        for p, v in zip(self.positions, values, strict=True):
            out[p.row, p.col] = v
        return out

    @property
    def manifest_name(self) -> str:
        return self.metadata.get("_manifest", MANIFEST_JSON)

    def position(self, row: int, col: int) -> GridPosition:
        """The :class:`GridPosition` at grid index ``(row, col)``."""
        n_rows, n_cols = self.grid_shape
        if not (0 <= row < n_rows and 0 <= col < n_cols):
            raise InvalidInputError(
                f"{self.root}: grid index ({row}, {col}) outside the {n_rows}×{n_cols} grid")
        try:
            return self._by_index[(row, col)]
        except KeyError:
            raise InvalidInputError(f"{self.root}: grid index ({row}, {col}) was not captured "
                                    f"(not in {self.manifest_name})") from None

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
        """Field angles ``(θx, θy)`` in degrees, ``(N, M, 2)`` (:meth:`_lattice`)."""
        return self._lattice("field_deg", (2,))

    def monitor_px(self) -> np.ndarray | None:
        """Monitor positions ``(x, y)``, ``(N, M, 2)`` (:meth:`_lattice`)."""
        return self._lattice("monitor_px", (2,))

    def exposures(self) -> np.ndarray | None:
        """Exposure times (s), ``(N, M)`` (:meth:`_lattice`)."""
        return self._lattice("exposure_s", ())

    def with_reference(self, index: tuple[int, int]) -> PsfGrid:
        """This grid with another reference ("centre") position; refused when it was not
        captured."""
        row, col = index
        if not self.has(row, col):
            raise InvalidInputError(f"{self.root}: reference {self.describe_index(index)} is "
                                    f"not a captured position of this {self.layout}")
        return replace(self, center_index=(row, col))

    def find_reference(self, text: str) -> tuple[int, int]:
        """The grid index named by ``--reference``: ``R,C`` (a lattice), ``#I`` or ``I`` (the
        I-th position of an irregular scan), or a file name of the manifest."""
        text = text.strip()
        for p in self.positions:
            if p.file == text:
                return p.row, p.col
        parts = [t.strip() for t in text.lstrip("#").split(",")]
        try:
            numbers = [int(t) for t in parts]
        except ValueError:
            numbers = []
        if len(numbers) == 1 and self.is_irregular:
            numbers = [0, numbers[0]]
        if len(numbers) != 2:
            raise InvalidInputError(f"--reference: expected R,C (grid row and column), a "
                                    f"position number of an irregular scan or a file name, "
                                    f"got {text!r}")
        index = (numbers[0], numbers[1])
        if not self.has(*index):
            raise InvalidInputError(f"--reference {text}: no captured position "
                                    f"{self.describe_index(index)} in {self.root}")
        return index

    def require_center(self) -> tuple[int, int]:
        """Grid index of the on-axis (reference) PSF; raises when the grid has none."""
        if self.center_index is None:
            n_rows, n_cols = self.grid_shape
            what = "irregular scan" if self.is_irregular else f"{n_rows}×{n_cols} grid"
            raise GridFormatError(
                f"{self.root / self.manifest_name}: the {what} has no centre "
                "position (no position at field (0, 0) and no odd-sized middle); add "
                "\"center\" to the manifest or name one with --reference")
        if not self.has(*self.center_index):
            raise GridFormatError(
                f"{self.root / self.manifest_name}: the centre position "
                f"{self.describe_index(self.center_index)} was not captured; name another "
                "reference with --reference R,C")
        return self.center_index


@contextlib.contextmanager
def grid_errors() -> Iterator[None]:
    """Within the block, an :class:`InvalidInputError` becomes a :class:`GridFormatError`."""
    try:
        yield
    except InvalidInputError as exc:
        raise GridFormatError(str(exc)) from None


def checked_dark(path: Path, image: np.ndarray) -> np.ndarray:
    """The dark frame, refused when it holds NaN/Inf (one check for every command)."""
    with grid_errors():
        return require_finite(image, f"{path}: dark frame")
