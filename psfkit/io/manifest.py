"""Parsing a PSF grid's ``manifest.json`` or ``manifest.csv`` (``docs/grid-format.md``) into
header fields and :class:`~psfkit.io.grid.GridPosition` entries; locating the centre."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from psfkit.errors import GridFormatError
from psfkit.io.grid import (
    FORMAT_NAME,
    FORMAT_VERSION,
    MANIFEST_CSV,
    MANIFEST_JSON,
    GridPosition,
    grid_errors,
)
from psfkit.io.json_documents import read_json_file
from psfkit.io.validation import MAX_GRID_CELLS

CSV_COLUMNS = ("file", "row", "col", "monitor_x_px", "monitor_y_px", "field_x_deg",
                "field_y_deg", "exposure_s", "role")
CENTRE_TOLERANCE = 1e-6
#: ``row``/``col`` of a parsed position of an irregular scan (no grid index in the manifest);
#: :func:`psfkit.io.grid_validation.read_grid` replaces it by ``(0, i)``.
NO_INDEX = -1
POSITION_KEYS = ("file", "row", "col", "monitor_px", "field_deg", "exposure_s")


def parse_pair(value: Any, where: str, name: str) -> tuple[float, float] | None:
    """Manifest field ``name`` as two finite numbers, or ``None`` when absent."""
    if value is None:
        return None
    try:
        pair = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise GridFormatError(f"{where}: '{name}' must be a list of two numbers") from None
    if len(pair) != 2 or not all(math.isfinite(v) for v in pair):
        raise GridFormatError(f"{where}: '{name}' must be two finite numbers, got {value!r}")
    return pair  # type: ignore[return-value]


def parse_index(value: Any, where: str, name: str) -> int:
    """Manifest field ``name`` as a non-negative integer (``3`` or ``"3"``, not ``3.5``)."""
    try:   # NaN (no number) fails the test below
        as_float = math.nan if isinstance(value, bool) or value is None else float(value)
    except (TypeError, ValueError):
        as_float = math.nan
    if not as_float.is_integer() or as_float < 0:
        raise GridFormatError(f"{where}: '{name}' must be a non-negative integer, got {value!r}")
    if as_float > MAX_GRID_CELLS:
        raise GridFormatError(f"{where}: '{name}' {value!r} exceeds the limit of "
                              f"{MAX_GRID_CELLS} positions a grid may have")
    return int(as_float)


def parse_positive(value: Any, where: str, name: str) -> float | None:
    """Manifest field ``name`` as a positive finite number, or ``None`` when absent/empty."""
    if value is None or value == "":
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise GridFormatError(f"{where}: '{name}' must be a number, got {value!r}") from None
    if not (math.isfinite(number) and number > 0):
        raise GridFormatError(f"{where}: '{name}' must be positive, got {value!r}")
    return number


def position_from_dict(entry: Any, where: str) -> GridPosition:
    """A :class:`GridPosition` from one manifest entry (``file``, ``row``, ``col``, ...)."""
    if not isinstance(entry, dict):
        raise GridFormatError(f"{where}: each position must be an object, got {entry!r}")
    file = entry.get("file")
    if not isinstance(file, str) or not file:
        raise GridFormatError(f"{where}: position without a 'file' name: {entry!r}")
    if Path(file).name != file:
        raise GridFormatError(f"{where}: file '{file}' must be a plain name inside the grid folder")
    unknown = sorted(str(k) for k in entry if k not in POSITION_KEYS)
    if unknown:
        raise GridFormatError(f"{where} ({file}): unknown key(s) {', '.join(unknown)} "
                              f"(allowed: {', '.join(POSITION_KEYS)})")
    has_row, has_col = (entry.get(k) not in (None, "") for k in ("row", "col"))
    if has_row != has_col:
        raise GridFormatError(f"{where} ({file}): give both 'row' and 'col' (a lattice) or "
                              "neither (an irregular scan)")
    return GridPosition(
        file=file,
        row=parse_index(entry.get("row"), f"{where} ({file})", "row") if has_row else NO_INDEX,
        col=parse_index(entry.get("col"), f"{where} ({file})", "col") if has_col else NO_INDEX,
        monitor_px=parse_pair(entry.get("monitor_px"), f"{where} ({file})", "monitor_px"),
        field_deg=parse_pair(entry.get("field_deg"), f"{where} ({file})", "field_deg"),
        exposure_s=parse_positive(entry.get("exposure_s"), f"{where} ({file})", "exposure_s"),
    )


def _parse_json(path: Path) -> tuple[dict[str, Any], list[GridPosition]]:
    with grid_errors():
        doc = read_json_file(path)
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
    positions = [position_from_dict(e, str(path)) for e in entries]
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
    columns = _csv_columns(path, rows[0])
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
        positions.append(position_from_dict(_csv_entry(row), where))
    return header, positions


def _csv_columns(path: Path, first_row: dict[str | None, Any]) -> set[str]:
    """The header's columns, checked against :data:`CSV_COLUMNS`."""
    columns = {c for c in first_row if c is not None}
    missing = {"file"} - columns
    if ("row" in columns) != ("col" in columns):
        missing |= {"row", "col"} - columns
    if missing:
        raise GridFormatError(f"{path}: missing column(s) {', '.join(sorted(missing))}")
    unknown = columns - set(CSV_COLUMNS)
    if unknown:
        raise GridFormatError(f"{path}: unknown column(s) {', '.join(sorted(unknown))} "
                              f"(allowed: {', '.join(CSV_COLUMNS)})")
    return columns


def _csv_entry(row: dict[str, str]) -> dict[str, Any]:
    """One PSF row as the manifest-JSON position it stands for (empty cells: absent)."""

    def pair(a: str, b: str) -> list[str] | None:
        va, vb = (row.get(a) or "").strip(), (row.get(b) or "").strip()
        if not va and not vb:
            return None
        return [va, vb]

    return {"file": (row.get("file") or "").strip(), "row": row.get("row"),
            "col": row.get("col"), "monitor_px": pair("monitor_x_px", "monitor_y_px"),
            "field_deg": pair("field_x_deg", "field_y_deg"),
            "exposure_s": (row.get("exposure_s") or "").strip() or None}


def parse_manifest(path: Path) -> tuple[dict[str, Any], list[GridPosition]]:
    """The header fields and the positions (in file order) of ``manifest.json`` or
    ``manifest.csv``; raises :class:`~psfkit.errors.GridFormatError` naming the problem."""
    return (_parse_json if path.suffix == ".json" else _parse_csv)(path)


def find_manifest(root: Path) -> Path:
    """``root/manifest.json`` or ``root/manifest.csv`` (exactly one must exist)."""
    json_path, csv_path = root / MANIFEST_JSON, root / MANIFEST_CSV
    if json_path.is_file() and csv_path.is_file():
        raise GridFormatError(f"{root}: has both {MANIFEST_JSON} and {MANIFEST_CSV}; keep one")
    if json_path.is_file():
        return json_path
    if csv_path.is_file():
        return csv_path
    raise GridFormatError(f"{root}: no {MANIFEST_JSON} or {MANIFEST_CSV} (not a PSF-grid folder)")


def locate_center(positions: list[GridPosition], grid_shape: tuple[int, int],
                   header: dict[str, Any], manifest: Path, irregular: bool = False
                   ) -> tuple[int, int] | None:
    """Grid index of the on-axis PSF: the header's ``center``, else the one position at field
    (or monitor) ``(0, 0)``, else the middle of an odd-sized lattice; ``None`` when none applies."""
    if header.get("center") is not None:
        value = header["center"]
        if isinstance(value, str):      # a file name (the way to name it in an irregular scan)
            named = [p for p in positions if p.file == value]
            if not named:
                raise GridFormatError(f"{manifest}: 'center' {value!r} is not a listed file")
            return named[0].row, named[0].col
        if not isinstance(value, list) or len(value) != 2:
            raise GridFormatError(f"{manifest}: 'center' must be [row, col], got {value!r}")
        row, col = (parse_index(v, str(manifest), "center") for v in value)
        if row >= grid_shape[0] or col >= grid_shape[1]:
            raise GridFormatError(f"{manifest}: 'center' {value} is outside the "
                                  f"{grid_shape[0]}×{grid_shape[1]} grid")
        return row, col
    for attr in ("field_deg", "monitor_px"):
        if all(getattr(p, attr) is not None for p in positions):
            on_axis = [p for p in positions
                       if max(abs(v) for v in getattr(p, attr)) < CENTRE_TOLERANCE]
            if len(on_axis) == 1:
                return on_axis[0].row, on_axis[0].col
            if len(on_axis) > 1:
                raise GridFormatError(f"{manifest}: several positions at field (0, 0): "
                                      f"{', '.join(p.file for p in on_axis)}")
    if not irregular and grid_shape[0] % 2 == 1 and grid_shape[1] % 2 == 1:
        return grid_shape[0] // 2, grid_shape[1] // 2
    return None
