"""Real-capture problems on a simulated grid: :func:`degrade_grid` copies a grid with some
positions dropped, over-exposed until they clip, or replaced by an empty capture; the ground
truth is copied as is, to check analyses of the degraded grid against it.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from psfkit.calibration.preprocess import saturation_level_for
from psfkit.errors import ConfigurationError
from psfkit.io.atomic import atomic_directory
from psfkit.io.grid import MANIFEST_JSON
from psfkit.io.grid_validation import read_grid
from psfkit.io.images import read_image, write_image
from psfkit.simulate.psf_grid import TRUTH_DIR

#: Exposure factor of a saturated capture: the bright caustic lines clip, several % of the PSF.
OVEREXPOSURE = 40.0


def degrade_grid(source: str | os.PathLike, out_dir: str | os.PathLike, *,
                 drop: Iterable[tuple[int, int]] = (),
                 saturate: Iterable[tuple[int, int]] = (),
                 empty: Iterable[tuple[int, int]] = (), overwrite: bool = False) -> Path:
    """Write a copy of the grid ``source`` with positions dropped, saturated or emptied.

    Parameters
    ----------
    source : path-like
        A lattice grid folder.
    out_dir : path-like
        Destination (created atomically).
    drop : iterable of (row, col)
        Removed from the manifest and the folder (``grid_shape`` keeps the full lattice).
    saturate : iterable of (row, col)
        Multiplied (above black level) by :data:`OVEREXPOSURE`, clipped at saturation.
    empty : iterable of (row, col)
        Replaced by the dark frame's noise (shifted), or the black level without a dark frame.
    """
    grid = read_grid(source, check_pixels=False)
    if grid.is_irregular:
        raise ConfigurationError(f"{source}: degrade_grid works on lattices")
    drop, saturate, empty = ({tuple(map(int, i)) for i in group}
                             for group in (drop, saturate, empty))
    for index in drop | saturate | empty:
        grid.position(*index)          # refuses an index the grid does not have
    level = saturation_level_for(grid)
    black = grid.black_level or 0.0
    dark = grid.load_dark()
    doc = json.loads((grid.root / MANIFEST_JSON).read_text(encoding="utf-8"))
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        for name in ([grid.dark_file] if grid.dark_file else []):
            shutil.copy2(grid.root / name, tmp / name)
        if (grid.root / TRUTH_DIR).is_dir():
            shutil.copytree(grid.root / TRUTH_DIR, tmp / TRUTH_DIR)
        kept = []
        for entry in doc["positions"]:
            index = (int(entry["row"]), int(entry["col"]))
            if index in drop:
                continue
            kept.append(entry)
            src, dst = grid.root / entry["file"], tmp / entry["file"]
            if index not in saturate and index not in empty:
                shutil.copy2(src, dst)
                continue
            raw = read_image(src, grid.channel_order)
            if index in saturate:
                top = float(level if level is not None else np.max(raw))
                image = np.clip(black + (raw.astype(np.float64) - black) * OVEREXPOSURE, 0, top)
            else:
                image = np.roll(dark, (7, 11), axis=(1, 2)) if dark is not None \
                    else np.full(raw.shape, black)
            write_image(dst, np.round(image).astype(raw.dtype))
        doc["positions"] = kept
        doc["grid_shape"] = list(grid.grid_shape)
        (tmp / MANIFEST_JSON).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return Path(out_dir)
