"""Writing a PSF grid atomically, one image at a time (:class:`GridWriter`)."""

from __future__ import annotations

import json
import os
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import GridFormatError, InvalidInputError
from psfkit.io.atomic import atomic_directory
from psfkit.io.grid import FORMAT_NAME, FORMAT_VERSION, MANIFEST_JSON, GridPosition
from psfkit.io.images import write_image


class GridWriter:
    """Write a PSF grid atomically, one image at a time; the folder appears at ``root`` only
    when the block ends without error and every grid index was written::

        with GridWriter(out, grid_shape=(9, 9), bit_depth=12) as writer:
            for ...:
                writer.add(row, col, image, field_deg=(tx, ty))
            writer.add_dark(dark)
            np.save(writer.folder / "ground_truth" / "x.npy", ...)   # extra files

    Parameters
    ----------
    root : path-like
        Destination folder (absent or empty, unless ``overwrite``).
    grid_shape : (int, int) or None
        Rows and columns of the lattice; ``None``: an irregular scan (:meth:`add_scan`).
    suffix : {".tiff", ".png", ".npy"}
        Image file type (TIFFs deflate-compressed, lossless).
    overwrite : bool
        Replace an existing folder.
    **header
        Extra manifest fields (``bit_depth``, ``black_level``, ``center``, metadata...).
    """

    def __init__(self, root: str | os.PathLike, grid_shape: tuple[int, int] | None,
                 suffix: str = ".tiff", overwrite: bool = False, **header: Any) -> None:
        if suffix not in (".tif", ".tiff", ".png", ".npy"):
            raise InvalidInputError(f"unsupported grid image type {suffix!r}")
        self.root = Path(root)
        self.grid_shape = None if grid_shape is None else (int(grid_shape[0]),
                                                            int(grid_shape[1]))
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
        return self._write(f"psf_r{row:02d}_c{col:02d}", row, col, image, fields)

    def add_scan(self, index: int, image: np.ndarray, **fields: Any) -> GridPosition:
        """Write the ``(C, H, W)`` image of position ``index`` of an irregular scan (give
        ``monitor_px`` or ``field_deg``)."""
        if self.grid_shape is not None:
            raise InvalidInputError(f"{self.root}: add_scan needs GridWriter(grid_shape=None)")
        return self._write(f"psf_{index:03d}", 0, index, image, fields)

    def _write(self, stem: str, row: int, col: int, image: np.ndarray,
               fields: dict[str, Any]) -> GridPosition:
        name = stem + self.suffix
        write_image(self.folder / name, image, compress=True)
        position = replace(GridPosition(file=name, row=row, col=col), **{
            k: (tuple(float(x) for x in v) if k in ("monitor_px", "field_deg") and v is not None
                else v) for k, v in fields.items()})
        self._positions[(row, col)] = position
        return position

    def add_dark(self, image: np.ndarray) -> None:
        """Write the dark frame (same shape and dtype as the PSFs)."""
        self._dark = f"dark{self.suffix}"
        write_image(self.folder / self._dark, image, compress=True)

    def _write_manifest(self) -> None:
        doc: dict[str, Any] = {"format": FORMAT_NAME, "version": FORMAT_VERSION}
        if self.grid_shape is not None:
            n_rows, n_cols = self.grid_shape
            missing = [(r, c) for r in range(n_rows) for c in range(n_cols)
                       if (r, c) not in self._positions]
            if missing:
                raise GridFormatError(f"{self.root}: grid incomplete, index {missing[0]} was "
                                      "never written")
            doc["grid_shape"] = list(self.grid_shape)
        if self._dark:
            doc["dark_frame"] = self._dark
        doc.update(self.header)
        doc["positions"] = [_position_to_dict(self._positions[k], self.grid_shape is None)
                            for k in sorted(self._positions)]
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


def _position_to_dict(p: GridPosition, scan: bool = False) -> dict[str, Any]:
    out: dict[str, Any] = {"file": p.file} if scan else {"file": p.file, "row": p.row,
                                                           "col": p.col}
    if p.monitor_px is not None:
        out["monitor_px"] = [round(v, 6) for v in p.monitor_px]
    if p.field_deg is not None:
        out["field_deg"] = [round(v, 9) for v in p.field_deg]
    if p.exposure_s is not None:
        out["exposure_s"] = p.exposure_s
    return out
