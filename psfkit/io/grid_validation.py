"""Reading a PSF-grid folder = validating all of it (:func:`read_grid`): manifest, grid
indices, files present and listed, image shapes and pixel types, pixel values, header fields.
Every problem is a :class:`~psfkit.errors.GridFormatError` naming the file."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import GridFormatError
from psfkit.io.grid import (
    FULL_LATTICE,
    INCOMPLETE_LATTICE,
    IRREGULAR,
    PsfGrid,
    checked_dark,
    grid_errors,
)
from psfkit.io.images import IMAGE_SUFFIXES, read_image
from psfkit.io.manifest import (
    NO_INDEX,
    find_manifest,
    locate_center,
    parse_index,
    parse_manifest,
    parse_positive,
)
from psfkit.io.validation import (
    MAX_GRID_CELLS,
    MIN_PSF_SIDE,
    finite_number,
    format_bytes,
    machine_memory_bytes,
)

#: Longest side (px) of the eigen fit's working copy of a PSF and of the characterization's
#: thumbnail (a test checks they agree with ``EigenFitOptions`` and ``THUMBNAIL_SIZE``).
WORKING_SIDE = 256
THUMBNAIL_SIDE = 160
#: Full-resolution float64 row and column weight-factor vectors the eigen fit keeps per
#: position and convention (basis "paper": 4).
FACTOR_VECTORS = 4
#: Bytes of the per-position records (numbers, coarse flow, excluded-position details).
RECORD_BYTES = 16 * 2**10
#: Bytes of the per-cell tables of a lattice (about 40 float64 numbers per cell).
CELL_BYTES = 512


def analysis_memory_bytes(grid_shape: tuple[int, int], n_positions: int,
                          image_shape: tuple[int, int, int]) -> int:
    """Bytes the analyses of a grid (``report``, ``fit-eigen``) hold, estimated before any
    image is read: per cell, the tables and the thumbnail; per captured position, the eigen
    fit's working copy (float32 + mask), its weight factors (both conventions) and records;
    once, the full-resolution normal equations of both conventions and ~16 images in flight.

    Parameters
    ----------
    grid_shape : (int, int)
        Cells of the lattice, ``(1, P)`` for an irregular scan.
    n_positions : int
        Captured positions.
    image_shape : (int, int, int)
        ``(C, H, W)`` of the images.
    """
    c, h, w = image_shape
    factor = max(1, -(-max(h, w) // THUMBNAIL_SIDE))
    per_cell = CELL_BYTES + 4 * (h // factor) * (w // factor)
    working = min(h, WORKING_SIDE) * min(w, WORKING_SIDE)
    per_position = (working * (4 * c + 1) + 2 * FACTOR_VECTORS * (h + w) * 8
                    + RECORD_BYTES)
    k = 3                                              # kernels of the default basis
    once = h * w * (2 * 8 * (k * (k + 1) // 2 + c * k) + 16 * 4 * c)
    return int(grid_shape[0]) * int(grid_shape[1]) * per_cell + n_positions * per_position \
        + once


def check_fits_in_memory(manifest: Path, grid_shape: tuple[int, int], n_positions: int,
                         image_shape: tuple[int, int, int], declared: bool,
                         irregular: bool) -> None:
    """Refuse, with a :class:`GridFormatError`, a grid whose analyses cannot fit in this
    machine's memory."""
    need = analysis_memory_bytes(grid_shape, n_positions, image_shape)
    have = machine_memory_bytes()
    if need <= have:
        return
    c, h, w = image_shape
    what = (f"grid_shape {list(grid_shape)}" if declared else
            "an irregular scan" if irregular else "a lattice")
    raise GridFormatError(
        f"{manifest}: {what} of {grid_shape[0]} x {grid_shape[1]} positions "
        f"({n_positions} captured) of {h} x {w} x {c} images needs about {format_bytes(need)} "
        f"of memory to analyse, more than this machine's {format_bytes(have)}; analyse the "
        "positions in parts (one manifest each) or bin the images")


def pixel_problem(path: Path, image: np.ndarray) -> str | None:
    """The one-line problem of a PSF frame's pixel values (NaN/Inf, all zero), or ``None``."""
    if np.issubdtype(image.dtype, np.floating):
        bad = int(np.count_nonzero(~np.isfinite(image)))
        if bad:
            return f"{path}: contains {bad} NaN/Inf pixel value(s)"
    if not np.any(image):
        return f"{path}: all-zero frame (nothing was captured)"
    return None


def _describe(shape: tuple[int, ...], dtype: np.dtype) -> str:
    c, h, w = shape
    return f"{h}×{w}×{c} {dtype}"


def _check_frame_size(path: Path, shape: tuple[int, ...]) -> None:
    """Refuse a frame smaller than ``MIN_PSF_SIDE`` (the first frame: all share its shape)."""
    h, w = shape[-2:]
    if min(h, w) < MIN_PSF_SIDE:
        raise GridFormatError(f"{path}: image of {h}×{w} px is too small to hold a PSF; "
                              f"registration needs at least {MIN_PSF_SIDE}×{MIN_PSF_SIDE} px "
                              "(the PSF and background around it)")


def read_grid(root: str | os.PathLike, check_pixels: bool = True,
              progress: bool = False, strict: bool = False) -> PsfGrid:
    """Read and validate a PSF-grid folder.

    Parameters
    ----------
    root : path-like
        The grid folder (holding ``manifest.json`` or ``manifest.csv``).
    check_pixels : bool
        Also read every image for NaN/Inf and all-zero frames: refused with ``strict``, else
        listed in :attr:`PsfGrid.frame_problems`. Without it only headers are checked.
    progress : bool
        Show a progress bar while checking images.
    strict : bool
        Refuse an incomplete lattice, an irregular scan and unusable frames.

    Raises
    ------
    GridFormatError
        Anything in the folder that breaks the format (the message names the file).
    """
    root = Path(root)
    _check_root(root)
    manifest = find_manifest(root)
    header, positions = parse_manifest(manifest)
    positions, irregular = _indexed_positions(positions, header, manifest, strict)
    seen_index, seen_file = _refuse_duplicates(positions, manifest)
    n_rows, n_cols, declared_shape = _grid_shape(positions, header, manifest)
    missing = [(r, c) for r in range(n_rows) for c in range(n_cols) if (r, c) not in seen_index]
    if missing and strict:
        listed = ", ".join(f"({r}, {c})" for r, c in missing[:5])
        more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
        raise GridFormatError(f"{manifest}: grid index {listed}{more} missing from the "
                              f"{n_rows}×{n_cols} grid")
    positions.sort(key=lambda p: (p.row, p.col))

    dark_file = _dark_file(header, manifest, seen_file)
    _check_folder_matches(root, manifest, seen_file | ({dark_file} if dark_file else set()))

    channel_order = header.get("channel_order", "RGB")
    if channel_order not in ("RGB", "BGR"):
        raise GridFormatError(f"{manifest}: 'channel_order' must be 'RGB' or 'BGR'")
    # the size of what the analyses will hold, from the first image's header, before the
    # images are read (the others must have its shape)
    check_fits_in_memory(manifest, (n_rows, n_cols), len(positions),
                         _peek(root / positions[0].file, channel_order)[0], declared_shape,
                         irregular)

    files = [p.file for p in positions] + ([dark_file] if dark_file else [])
    ref_shape, ref_dtype, frame_problems = _check_images(
        root, files, channel_order, dark_file, check_pixels=check_pixels, strict=strict,
        progress=progress)

    bit_depth, black_level, pitch = _header_fields(header, manifest)
    known = {"format", "version", "grid_shape", "channel_order", "bit_depth", "black_level",
             "dark_frame", "pixel_pitch_um", "center"}
    metadata = {k: v for k, v in header.items() if k not in known}
    metadata["_manifest"] = manifest.name
    if frame_problems:
        metadata["_frame_problems"] = frame_problems
    return PsfGrid(
        root=root,
        positions=tuple(positions),
        grid_shape=(n_rows, n_cols),
        image_shape=ref_shape,
        dtype=ref_dtype,
        channels=("L",) if ref_shape[0] == 1 else ("R", "G", "B"),
        channel_order=channel_order,
        dark_file=dark_file,
        black_level=black_level,
        bit_depth=bit_depth,
        pixel_pitch_um=pitch,
        center_index=locate_center(positions, (n_rows, n_cols), header, manifest, irregular),
        metadata=metadata,
        layout=IRREGULAR if irregular else INCOMPLETE_LATTICE if missing else FULL_LATTICE,
    )


def _check_root(root: Path) -> None:
    if not root.exists():
        raise GridFormatError(f"{root}: no such grid folder")
    if not root.is_dir():
        raise GridFormatError(f"{root}: not a folder (a PSF grid is a folder with a manifest)")


def _indexed_positions(positions: list[Any], header: dict[str, Any], manifest: Path,
                       strict: bool) -> tuple[list[Any], bool]:
    """The positions with their grid indices, and whether the scan is irregular."""
    indexed = [p.row != NO_INDEX for p in positions]
    if any(indexed) and not all(indexed):
        bare = positions[indexed.index(False)].file
        raise GridFormatError(f"{manifest}: {bare} has no row/col but other positions do; give "
                              "every position a grid index (a lattice) or none (an irregular "
                              "scan)")
    irregular = not any(indexed)
    if irregular:
        positions = _irregular_positions(positions, header, manifest, strict)
    return positions, irregular


def _refuse_duplicates(positions: list[Any], manifest: Path
                       ) -> tuple[dict[tuple[int, int], str], set[str]]:
    """The file of every grid index, and the set of files; repeats are refused."""
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
    return seen_index, seen_file


def _grid_shape(positions: list[Any], header: dict[str, Any], manifest: Path
                ) -> tuple[int, int, bool]:
    """``(rows, cols, declared)``: the manifest's ``grid_shape`` (holding every position), else
    the positions' extent; at most ``MAX_GRID_CELLS``."""
    n_rows = max(p.row for p in positions) + 1
    n_cols = max(p.col for p in positions) + 1
    declared_shape = header.get("grid_shape") is not None
    if declared_shape:
        gs = header["grid_shape"]
        if not (isinstance(gs, list) and len(gs) == 2):
            raise GridFormatError(f"{manifest}: 'grid_shape' must be [rows, cols], got {gs!r}")
        declared = tuple(parse_index(v, str(manifest), "grid_shape") for v in gs)
        if declared[0] < n_rows or declared[1] < n_cols:
            raise GridFormatError(f"{manifest}: positions reach index ({n_rows - 1}, "
                                  f"{n_cols - 1}) beyond grid_shape {list(declared)}")
        n_rows, n_cols = declared
    if n_rows * n_cols > MAX_GRID_CELLS:
        raise GridFormatError(f"{manifest}: {'grid_shape' if declared_shape else 'grid'} "
                              f"[{n_rows}, {n_cols}] declares {n_rows * n_cols} positions, "
                              f"more than the {MAX_GRID_CELLS} a grid may have")
    return n_rows, n_cols, declared_shape


def _dark_file(header: dict[str, Any], manifest: Path, psf_files: set[str]) -> str | None:
    """The manifest's ``dark_frame``: a file name in the folder that is not a PSF."""
    dark_file = header.get("dark_frame")
    if dark_file is not None and (not isinstance(dark_file, str) or Path(dark_file).name
                                  != dark_file):
        raise GridFormatError(f"{manifest}: 'dark_frame' must be a file name in the folder")
    if dark_file is not None and dark_file in psf_files:
        raise GridFormatError(f"{manifest}: {dark_file} is both a PSF and the dark frame")
    return dark_file


def _check_folder_matches(root: Path, manifest: Path, listed: set[str]) -> None:
    """Every listed file is in the folder, and every image file in the folder is listed."""
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


def _check_images(root: Path, files: list[str], channel_order: str, dark_file: str | None, *,
                  check_pixels: bool, strict: bool, progress: bool
                  ) -> tuple[tuple[int, int, int], np.dtype, dict[str, str]]:
    """``(shape, dtype, problems)`` of the images, all of the first's shape and dtype."""
    ref_shape: tuple[int, int, int] | None = None
    ref_dtype: np.dtype | None = None
    ref_file = ""
    frame_problems: dict[str, str] = {}
    iterator: Any = files
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(files, desc="checking grid", unit="img", leave=False)
    for name in iterator:
        path = root / name
        image = _read_checked(path, channel_order) if check_pixels else None
        shape, dtype = ((image.shape, image.dtype) if image is not None
                        else _peek(path, channel_order))
        if ref_shape is None:
            _check_frame_size(path, shape)
            ref_shape, ref_dtype, ref_file = shape, dtype, name  # type: ignore[assignment]
        elif shape != ref_shape or dtype != ref_dtype:
            what = "shape" if shape != ref_shape else "pixel type"
            raise GridFormatError(
                f"{path}: {what} {_describe(shape, dtype)} differs from {ref_file} "
                f"({_describe(ref_shape, ref_dtype)})")
        if image is None:
            continue
        if name == dark_file:
            checked_dark(path, image)
            continue
        problem = pixel_problem(path, image)
        if problem is not None and strict:
            raise GridFormatError(problem)
        if problem is not None:    # flagged: the analyses exclude this position
            frame_problems[name] = problem
    assert ref_shape is not None and ref_dtype is not None
    return ref_shape, ref_dtype, frame_problems


def _read_checked(path: Path, channel_order: str) -> np.ndarray:
    with grid_errors():
        return read_image(path, channel_order)


def _header_fields(header: dict[str, Any], manifest: Path
                   ) -> tuple[int | None, float | None, float | None]:
    """The manifest's optional ``bit_depth``, ``black_level`` and ``pixel_pitch_um``."""
    bit_depth = header.get("bit_depth")
    if bit_depth is not None and (isinstance(bit_depth, bool) or not isinstance(bit_depth, int)
                                  or not 1 <= bit_depth <= 32):
        raise GridFormatError(f"{manifest}: 'bit_depth' must be an integer in 1..32")
    black_level = header.get("black_level")
    if black_level is not None:
        with grid_errors():  # at most the largest stored value (2^32 for any container)
            black_level = float(finite_number(black_level, f"{manifest}: 'black_level'", 0.0,
                                              2.0**32))
    pitch = header.get("pixel_pitch_um")
    if pitch is not None:
        pitch = parse_positive(pitch, str(manifest), "pixel_pitch_um")
    return bit_depth, black_level, pitch


def _irregular_positions(positions: list[Any], header: dict[str, Any], manifest: Path,
                         strict: bool) -> list[Any]:
    """An irregular scan's positions as row 0, column = place in the manifest; all located by
    ``monitor_px`` or all by ``field_deg``."""
    from dataclasses import replace

    if strict:
        raise GridFormatError(f"{manifest}: positions have no row/col (an irregular scan); "
                              "--strict needs a full lattice")
    if header.get("grid_shape") is not None:
        raise GridFormatError(f"{manifest}: 'grid_shape' describes a lattice, but the "
                              "positions have no row/col (an irregular scan); remove one")
    if not (all(p.monitor_px is not None for p in positions)
            or all(p.field_deg is not None for p in positions)):
        lacking = next(p.file for p in positions if p.monitor_px is None or p.field_deg is None)
        raise GridFormatError(f"{manifest}: an irregular scan needs 'monitor_px' or 'field_deg' "
                              f"for every position ({lacking} has neither, or the positions "
                              "mix the two)")
    return [replace(p, row=0, col=i) for i, p in enumerate(positions)]


def _peek(path: Path, channel_order: str) -> tuple[tuple[int, int, int], np.dtype]:
    """Shape ``(C, H, W)`` and dtype of an image without decoding all pixels where possible."""
    if path.suffix.lower() != ".npy":
        image = _read_checked(path, channel_order)
        return image.shape, image.dtype  # type: ignore[return-value]
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:
        raise GridFormatError(f"{path}: not a readable image ({exc})") from None
    shape = array.shape
    if len(shape) == 2:
        return (1, *shape), array.dtype
    if len(shape) == 3 and shape[2] in (1, 3):
        return (shape[2], shape[0], shape[1]), array.dtype
    raise GridFormatError(f"{path}: expected (H, W) or (H, W, C) with C in (1, 3), got {shape}")
