"""The PSF-grid folder format: a folder of point-source images plus a manifest.

A grid is what a lab hands over after displaying a point at N × M field positions and
capturing the camera's response at each. The format is documented in ``docs/grid-format.md``;
in short::

    grid/
      manifest.json            (or manifest.csv)
      psf_r00_c00.tiff ...     one image per grid position: 16-bit TIFF/PNG or .npy, mono or RGB
      dark.tiff                optional dark / black frame, same shape and type

``read_grid`` validates the whole folder before anything is computed and raises
:class:`~psfkit.errors.GridFormatError` naming the file and the problem. ``GridWriter``
writes a grid atomically (into a temporary folder renamed into place when complete).
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import GridFormatError, InvalidInputError
from psfkit.io.atomic import atomic_directory
from psfkit.io.images import IMAGE_SUFFIXES, read_image, write_image
from psfkit.validation import MAX_GRID_SIDE, finite_number, load_json_document, require_finite

FORMAT_NAME = "psfkit-grid"
FORMAT_VERSION = 1
MANIFEST_JSON = "manifest.json"
MANIFEST_CSV = "manifest.csv"
_CSV_COLUMNS = ("file", "row", "col", "monitor_x_px", "monitor_y_px", "field_x_deg",
                "field_y_deg", "exposure_s", "role")
_CENTRE_TOL = 1e-6
_POSITION_KEYS = ("file", "row", "col", "monitor_px", "field_deg", "exposure_s")


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
        return read_image(self.path(row, col), self.channel_order).astype(np.float32)

    def load_dark(self) -> np.ndarray | None:
        """The dark frame as ``(C, H, W)`` float32, or ``None`` when the grid has none."""
        if self.dark_file is None:
            return None
        path = self.root / self.dark_file
        return _checked_dark(path, read_image(path, self.channel_order)).astype(np.float32)

    def iter_images(self) -> Iterator[tuple[GridPosition, np.ndarray]]:
        """Yield ``(position, image)`` in row-major order, one image in memory at a time."""
        for pos in self.positions:
            yield pos, self.load(pos.row, pos.col)

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


# --------------------------------------------------------------------------- parsing helpers


def _pair(value: Any, where: str, name: str) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        pair = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise GridFormatError(f"{where}: '{name}' must be a list of two numbers") from None
    if len(pair) != 2 or not all(math.isfinite(v) for v in pair):
        raise GridFormatError(f"{where}: '{name}' must be two finite numbers, got {value!r}")
    return pair  # type: ignore[return-value]


def _index(value: Any, where: str, name: str) -> int:
    if isinstance(value, bool) or value is None:
        raise GridFormatError(f"{where}: '{name}' must be a non-negative integer, got {value!r}")
    try:
        as_float = float(value)
    except (TypeError, ValueError):
        raise GridFormatError(
            f"{where}: '{name}' must be a non-negative integer, got {value!r}") from None
    if not as_float.is_integer() or as_float < 0:
        raise GridFormatError(f"{where}: '{name}' must be a non-negative integer, got {value!r}")
    if as_float > MAX_GRID_SIDE:
        raise GridFormatError(f"{where}: '{name}' {value!r} exceeds the limit of "
                              f"{MAX_GRID_SIDE} x {MAX_GRID_SIDE} positions")
    return int(as_float)


def _positive(value: Any, where: str, name: str) -> float | None:
    if value is None or value == "":
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise GridFormatError(f"{where}: '{name}' must be a number, got {value!r}") from None
    if not (math.isfinite(number) and number > 0):
        raise GridFormatError(f"{where}: '{name}' must be positive, got {value!r}")
    return number


def _position_from_dict(entry: Any, where: str) -> GridPosition:
    if not isinstance(entry, dict):
        raise GridFormatError(f"{where}: each position must be an object, got {entry!r}")
    file = entry.get("file")
    if not isinstance(file, str) or not file:
        raise GridFormatError(f"{where}: position without a 'file' name: {entry!r}")
    if Path(file).name != file:
        raise GridFormatError(f"{where}: file '{file}' must be a plain name inside the grid folder")
    unknown = sorted(str(k) for k in entry if k not in _POSITION_KEYS)
    if unknown:
        raise GridFormatError(f"{where} ({file}): unknown key(s) {', '.join(unknown)} "
                              f"(allowed: {', '.join(_POSITION_KEYS)})")
    return GridPosition(
        file=file,
        row=_index(entry.get("row"), f"{where} ({file})", "row"),
        col=_index(entry.get("col"), f"{where} ({file})", "col"),
        monitor_px=_pair(entry.get("monitor_px"), f"{where} ({file})", "monitor_px"),
        field_deg=_pair(entry.get("field_deg"), f"{where} ({file})", "field_deg"),
        exposure_s=_positive(entry.get("exposure_s"), f"{where} ({file})", "exposure_s"),
    )


def _parse_json(path: Path) -> tuple[dict[str, Any], list[GridPosition]]:
    try:
        doc = load_json_document(path.read_bytes(), str(path))
    except GridFormatError:
        raise
    except InvalidInputError as exc:
        raise GridFormatError(str(exc)) from None
    if not isinstance(doc, dict):
        raise GridFormatError(f"{path}: top level must be an object with a 'positions' list")
    fmt = doc.get("format", FORMAT_NAME)
    if fmt != FORMAT_NAME:
        raise GridFormatError(f"{path}: format is {fmt!r}, expected {FORMAT_NAME!r}")
    version = doc.get("version", FORMAT_VERSION)
    if isinstance(version, bool) or version != FORMAT_VERSION:
        raise GridFormatError(
            f"{path}: grid format version {version!r} is not supported (this reader: "
            f"{FORMAT_VERSION})")
    entries = doc.get("positions")
    if not isinstance(entries, list) or not entries:
        raise GridFormatError(f"{path}: needs a non-empty 'positions' list")
    positions = [_position_from_dict(e, str(path)) for e in entries]
    header = {k: v for k, v in doc.items() if k != "positions"}
    return header, positions


def _parse_csv(path: Path) -> tuple[dict[str, Any], list[GridPosition]]:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.DictReader(
                line for line in fh if line.strip() and not line.lstrip().startswith("#"))]
    except (UnicodeDecodeError, csv.Error) as exc:
        raise GridFormatError(f"{path}: not a readable CSV file ({exc})") from None
    if not rows:
        raise GridFormatError(f"{path}: no rows (needs a header line with file,row,col)")
    columns = {c for c in rows[0] if c is not None}
    missing = {"file", "row", "col"} - columns
    if missing:
        raise GridFormatError(f"{path}: missing column(s) {', '.join(sorted(missing))}")
    unknown = columns - set(_CSV_COLUMNS)
    if unknown:
        raise GridFormatError(f"{path}: unknown column(s) {', '.join(sorted(unknown))} "
                              f"(allowed: {', '.join(_CSV_COLUMNS)})")
    header: dict[str, Any] = {}
    positions = []
    for line_no, row in enumerate(rows, start=2):
        where = f"{path} line {line_no}"
        if None in row:  # DictReader files cells beyond the header under the key None
            raise GridFormatError(f"{where}: {len(row[None])} cell(s) more than the "
                                  f"{len(columns)} columns of the header")
        role = (row.get("role") or "psf").strip().lower()
        if role == "dark":
            if "dark_frame" in header:
                raise GridFormatError(f"{where}: a second dark frame")
            header["dark_frame"] = row["file"].strip()
            continue
        if role != "psf":
            raise GridFormatError(f"{where}: role must be 'psf' or 'dark', got {role!r}")

        def pair(a: str, b: str, row: dict[str, str] = row) -> list[str] | None:
            va, vb = (row.get(a) or "").strip(), (row.get(b) or "").strip()
            if not va and not vb:
                return None
            return [va, vb]

        entry = {"file": (row.get("file") or "").strip(), "row": row.get("row"),
                 "col": row.get("col"), "monitor_px": pair("monitor_x_px", "monitor_y_px"),
                 "field_deg": pair("field_x_deg", "field_y_deg"),
                 "exposure_s": (row.get("exposure_s") or "").strip() or None}
        positions.append(_position_from_dict(entry, where))
    return header, positions


def _find_manifest(root: Path) -> Path:
    json_path, csv_path = root / MANIFEST_JSON, root / MANIFEST_CSV
    if json_path.is_file() and csv_path.is_file():
        raise GridFormatError(f"{root}: has both {MANIFEST_JSON} and {MANIFEST_CSV}; keep one")
    if json_path.is_file():
        return json_path
    if csv_path.is_file():
        return csv_path
    raise GridFormatError(f"{root}: no {MANIFEST_JSON} or {MANIFEST_CSV} (not a PSF-grid folder)")


def _locate_center(positions: list[GridPosition], grid_shape: tuple[int, int],
                   header: dict[str, Any], manifest: Path) -> tuple[int, int] | None:
    if header.get("center") is not None:
        value = header["center"]
        if not isinstance(value, list) or len(value) != 2:
            raise GridFormatError(f"{manifest}: 'center' must be [row, col], got {value!r}")
        row, col = (_index(v, str(manifest), "center") for v in value)
        if row >= grid_shape[0] or col >= grid_shape[1]:
            raise GridFormatError(f"{manifest}: 'center' {value} is outside the "
                                  f"{grid_shape[0]}×{grid_shape[1]} grid")
        return row, col
    for attr in ("field_deg", "monitor_px"):
        if all(getattr(p, attr) is not None for p in positions):
            on_axis = [p for p in positions
                       if max(abs(v) for v in getattr(p, attr)) < _CENTRE_TOL]
            if len(on_axis) == 1:
                return on_axis[0].row, on_axis[0].col
            if len(on_axis) > 1:
                raise GridFormatError(f"{manifest}: several positions at field (0, 0): "
                                      f"{', '.join(p.file for p in on_axis)}")
    if grid_shape[0] % 2 == 1 and grid_shape[1] % 2 == 1:
        return grid_shape[0] // 2, grid_shape[1] // 2
    return None


def _check_pixels(path: Path, image: np.ndarray) -> None:
    if np.issubdtype(image.dtype, np.floating):
        bad = int(np.count_nonzero(~np.isfinite(image)))
        if bad:
            raise GridFormatError(f"{path}: contains {bad} NaN/Inf pixel value(s)")
    if not np.any(image):
        raise GridFormatError(f"{path}: all-zero frame (nothing was captured)")


def _checked_dark(path: Path, image: np.ndarray) -> np.ndarray:
    """The dark frame, refused when it holds NaN/Inf (one check for every command)."""
    try:
        return require_finite(image, f"{path}: dark frame")
    except InvalidInputError as exc:
        raise GridFormatError(str(exc)) from None


def _describe(shape: tuple[int, ...], dtype: np.dtype) -> str:
    c, h, w = shape
    return f"{h}×{w}×{c} {dtype}"


def read_grid(root: str | os.PathLike, check_pixels: bool = True,
              progress: bool = False) -> PsfGrid:
    """Read and validate a PSF-grid folder.

    Parameters
    ----------
    root : path-like
        The grid folder (holding ``manifest.json`` or ``manifest.csv``).
    check_pixels : bool
        Also read every image to reject NaN/Inf values and all-zero frames (one image in
        memory at a time). Without it only headers, shapes and dtypes are checked.
    progress : bool
        Show a progress bar while checking images.

    Returns
    -------
    PsfGrid

    Raises
    ------
    GridFormatError
        Missing or malformed manifest, missing/duplicate grid index or file, missing image,
        files in the folder that the manifest does not list, non-image files, mixed shapes or
        dtypes, NaN/Inf values, all-zero frames.
    """
    root = Path(root)
    if not root.exists():
        raise GridFormatError(f"{root}: no such grid folder")
    if not root.is_dir():
        raise GridFormatError(f"{root}: not a folder (a PSF grid is a folder with a manifest)")
    manifest = _find_manifest(root)
    header, positions = (_parse_json if manifest.suffix == ".json" else _parse_csv)(manifest)

    seen_index: dict[tuple[int, int], str] = {}
    seen_file: set[str] = set()
    for p in positions:
        if (p.row, p.col) in seen_index:
            raise GridFormatError(f"{manifest}: grid index ({p.row}, {p.col}) appears twice "
                                  f"({seen_index[(p.row, p.col)]} and {p.file})")
        if p.file in seen_file:
            raise GridFormatError(f"{manifest}: file {p.file} is listed twice")
        seen_index[(p.row, p.col)] = p.file
        seen_file.add(p.file)

    n_rows = max(p.row for p in positions) + 1
    n_cols = max(p.col for p in positions) + 1
    if header.get("grid_shape") is not None:
        gs = header["grid_shape"]
        if not (isinstance(gs, list) and len(gs) == 2):
            raise GridFormatError(f"{manifest}: 'grid_shape' must be [rows, cols], got {gs!r}")
        declared = tuple(_index(v, str(manifest), "grid_shape") for v in gs)
        if declared[0] < n_rows or declared[1] < n_cols:
            raise GridFormatError(f"{manifest}: positions reach index ({n_rows - 1}, "
                                  f"{n_cols - 1}) beyond grid_shape {list(declared)}")
        n_rows, n_cols = declared
    if n_rows > MAX_GRID_SIDE or n_cols > MAX_GRID_SIDE:
        raise GridFormatError(f"{manifest}: grid of {n_rows} x {n_cols} positions exceeds the "
                              f"limit of {MAX_GRID_SIDE} x {MAX_GRID_SIDE} positions")
    missing = [(r, c) for r in range(n_rows) for c in range(n_cols) if (r, c) not in seen_index]
    if missing:
        listed = ", ".join(f"({r}, {c})" for r, c in missing[:5])
        more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
        raise GridFormatError(f"{manifest}: grid index {listed}{more} missing from the "
                              f"{n_rows}×{n_cols} grid")
    positions.sort(key=lambda p: (p.row, p.col))

    dark_file = header.get("dark_frame")
    if dark_file is not None and (not isinstance(dark_file, str) or Path(dark_file).name
                                  != dark_file):
        raise GridFormatError(f"{manifest}: 'dark_frame' must be a file name in the folder")
    if dark_file is not None and dark_file in seen_file:
        raise GridFormatError(f"{manifest}: {dark_file} is both a PSF and the dark frame")

    listed = seen_file | ({dark_file} if dark_file else set())
    for name in sorted(listed):
        if not (root / name).is_file():
            raise GridFormatError(f"{root / name}: listed in {manifest.name} but missing")
    unlisted = sorted(f.name for f in root.iterdir() if f.is_file()
                      and f.suffix.lower() in IMAGE_SUFFIXES and f.name not in listed)
    if unlisted:
        shown = ", ".join(unlisted[:3]) + (f" and {len(unlisted) - 3} more"
                                           if len(unlisted) > 3 else "")
        raise GridFormatError(f"{manifest}: does not match the folder: image file(s) {shown} "
                              "not listed")

    channel_order = header.get("channel_order", "RGB")
    if channel_order not in ("RGB", "BGR"):
        raise GridFormatError(f"{manifest}: 'channel_order' must be 'RGB' or 'BGR'")

    ref_shape: tuple[int, int, int] | None = None
    ref_dtype: np.dtype | None = None
    ref_file = ""
    files = [p.file for p in positions] + ([dark_file] if dark_file else [])
    iterator: Any = files
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(files, desc="checking grid", unit="img", leave=False)
    for name in iterator:
        path = root / name
        if check_pixels:
            try:
                image = read_image(path, channel_order)
            except InvalidInputError as exc:
                raise GridFormatError(str(exc)) from None
            shape, dtype = image.shape, image.dtype
        else:
            shape, dtype = _peek(path, channel_order)
        if ref_shape is None:
            ref_shape, ref_dtype, ref_file = shape, dtype, name  # type: ignore[assignment]
        elif shape != ref_shape or dtype != ref_dtype:
            what = "shape" if shape != ref_shape else "pixel type"
            raise GridFormatError(
                f"{path}: {what} {_describe(shape, dtype)} differs from {ref_file} "
                f"({_describe(ref_shape, ref_dtype)})")
        if check_pixels and name != dark_file:
            _check_pixels(path, image)
        if check_pixels and name == dark_file:
            _checked_dark(path, image)
    assert ref_shape is not None and ref_dtype is not None

    channels = ("L",) if ref_shape[0] == 1 else ("R", "G", "B")
    bit_depth = header.get("bit_depth")
    if bit_depth is not None and (isinstance(bit_depth, bool) or not isinstance(bit_depth, int)
                                  or not 1 <= bit_depth <= 32):
        raise GridFormatError(f"{manifest}: 'bit_depth' must be an integer in 1..32")
    black_level = header.get("black_level")
    if black_level is not None:
        try:  # a black level is at most the largest stored value (2^32 for any container)
            black_level = finite_number(black_level, f"{manifest}: 'black_level'", 0.0, 2.0**32)
        except InvalidInputError as exc:
            raise GridFormatError(str(exc)) from None
    pitch = header.get("pixel_pitch_um")
    if pitch is not None:
        pitch = _positive(pitch, str(manifest), "pixel_pitch_um")
    known = {"format", "version", "grid_shape", "channel_order", "bit_depth", "black_level",
             "dark_frame", "pixel_pitch_um", "center"}
    metadata = {k: v for k, v in header.items() if k not in known}
    metadata["_manifest"] = manifest.name
    return PsfGrid(
        root=root,
        positions=tuple(positions),
        grid_shape=(n_rows, n_cols),
        image_shape=ref_shape,
        dtype=ref_dtype,
        channels=channels,
        channel_order=channel_order,
        dark_file=dark_file,
        black_level=None if black_level is None else float(black_level),
        bit_depth=bit_depth,
        pixel_pitch_um=pitch,
        center_index=_locate_center(positions, (n_rows, n_cols), header, manifest),
        metadata=metadata,
    )


def _peek(path: Path, channel_order: str) -> tuple[tuple[int, int, int], np.dtype]:
    """Shape ``(C, H, W)`` and dtype of an image without decoding all pixels where possible."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            array = np.load(path, mmap_mode="r", allow_pickle=False)
            shape = array.shape
            if len(shape) == 2:
                return (1, *shape), array.dtype
            if len(shape) == 3 and shape[2] in (1, 3):
                return (shape[2], shape[0], shape[1]), array.dtype
            raise InvalidInputError(f"{path}: expected (H, W) or (H, W, C) with C in (1, 3), "
                                    f"got {shape}")
    except InvalidInputError as exc:
        raise GridFormatError(str(exc)) from None
    except Exception as exc:
        raise GridFormatError(f"{path}: not a readable image ({exc})") from None
    try:
        image = read_image(path, channel_order)
    except InvalidInputError as exc:
        raise GridFormatError(str(exc)) from None
    return image.shape, image.dtype  # type: ignore[return-value]


# --------------------------------------------------------------------------- writing


class GridWriter:
    """Write a PSF grid atomically, one image at a time.

    Use as a context manager; the folder appears at ``root`` only when the block ends without
    error and every grid index has been written::

        with GridWriter(out, grid_shape=(9, 9), bit_depth=12) as writer:
            for ...:
                writer.add(row, col, image, field_deg=(tx, ty))
            writer.add_dark(dark)
            np.save(writer.folder / "ground_truth" / "x.npy", ...)   # extra files

    Parameters
    ----------
    root : path-like
        Destination folder (must not exist or be empty, unless ``overwrite``).
    grid_shape : (int, int)
        Number of rows and columns.
    suffix : {".tiff", ".png", ".npy"}
        Image file type.
    overwrite : bool
        Replace an existing folder.
    **header
        Extra manifest fields (``bit_depth``, ``black_level``, ``pixel_pitch_um``, ``center``,
        ``monitor``, free-form metadata such as ``simulation``).
    """

    def __init__(self, root: str | os.PathLike, grid_shape: tuple[int, int],
                 suffix: str = ".tiff", overwrite: bool = False, **header: Any) -> None:
        if suffix not in (".tif", ".tiff", ".png", ".npy"):
            raise InvalidInputError(f"unsupported grid image type {suffix!r}")
        self.root = Path(root)
        self.grid_shape = (int(grid_shape[0]), int(grid_shape[1]))
        self.suffix = suffix
        self.overwrite = overwrite
        self.header = header
        self._positions: dict[tuple[int, int], GridPosition] = {}
        self._dark: str | None = None
        self._context: Any = None
        self.folder: Path = Path()

    def __enter__(self) -> GridWriter:
        self._context = atomic_directory(self.root, overwrite=self.overwrite)
        self.folder = self._context.__enter__()
        return self

    def add(self, row: int, col: int, image: np.ndarray, **fields: Any) -> GridPosition:
        """Write the ``(C, H, W)`` image for grid index ``(row, col)``."""
        name = f"psf_r{row:02d}_c{col:02d}{self.suffix}"
        write_image(self.folder / name, image)
        position = replace(GridPosition(file=name, row=row, col=col), **{
            k: (tuple(float(x) for x in v) if k in ("monitor_px", "field_deg") and v is not None
                else v) for k, v in fields.items()})
        self._positions[(row, col)] = position
        return position

    def add_dark(self, image: np.ndarray) -> None:
        """Write the dark frame (same shape and dtype as the PSFs)."""
        self._dark = f"dark{self.suffix}"
        write_image(self.folder / self._dark, image)

    def _write_manifest(self) -> None:
        n_rows, n_cols = self.grid_shape
        missing = [(r, c) for r in range(n_rows) for c in range(n_cols)
                   if (r, c) not in self._positions]
        if missing:
            raise GridFormatError(f"{self.root}: grid incomplete, index {missing[0]} was "
                                    "never written")
        doc: dict[str, Any] = {"format": FORMAT_NAME, "version": FORMAT_VERSION,
                               "grid_shape": list(self.grid_shape)}
        if self._dark:
            doc["dark_frame"] = self._dark
        doc.update(self.header)
        doc["positions"] = [_position_to_dict(self._positions[k]) for k in sorted(self._positions)]
        (self.folder / MANIFEST_JSON).write_text(json.dumps(doc, indent=1) + "\n",
                                                 encoding="utf-8")

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> bool:
        if exc_type is None:
            try:
                self._write_manifest()
            except BaseException:
                self._context.__exit__(*sys.exc_info())
                raise
        return bool(self._context.__exit__(exc_type, exc, tb))


def _position_to_dict(p: GridPosition) -> dict[str, Any]:
    out: dict[str, Any] = {"file": p.file, "row": p.row, "col": p.col}
    if p.monitor_px is not None:
        out["monitor_px"] = [round(v, 6) for v in p.monitor_px]
    if p.field_deg is not None:
        out["field_deg"] = [round(v, 9) for v in p.field_deg]
    if p.exposure_s is not None:
        out["exposure_s"] = p.exposure_s
    return out
