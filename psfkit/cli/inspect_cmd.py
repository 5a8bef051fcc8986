"""``psfkit info``: validate a PSF-grid folder and summarise it."""

from __future__ import annotations

import argparse

import numpy as np

from psfkit.io import read_grid


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="validate a PSF grid and print a summary",
                       description="Read and validate a PSF-grid folder (manifest and every "
                                   "image) and print what it holds.")
    p.add_argument("grid", help="PSF-grid folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    grid = read_grid(args.grid, progress=not args.quiet)
    c, h, w = grid.image_shape
    print(f"grid:      {grid.root}")
    print(f"positions: {grid.grid_shape[0]} x {grid.grid_shape[1]} ({len(grid.positions)} "
          f"images, manifest {grid.manifest_name})")
    print(f"images:    {h} x {w} x {c} ({'/'.join(grid.channels)}), {grid.dtype}"
          + (f", {grid.bit_depth}-bit data" if grid.bit_depth else ""))
    print(f"centre:    {grid.center_index if grid.center_index else 'none'}")
    fields = grid.field_deg()
    if fields is not None:
        print(f"field:     x {fields[..., 0].min():+.2f}..{fields[..., 0].max():+.2f} deg, "
              f"y {fields[..., 1].min():+.2f}..{fields[..., 1].max():+.2f} deg")
    exposures = grid.exposures()
    if exposures is not None:
        print(f"exposure:  {np.min(exposures):g}..{np.max(exposures):g} s")
    print(f"dark:      {grid.dark_file or 'none'}"
          + (f", black level {grid.black_level:g}" if grid.black_level is not None else ""))
    return 0
