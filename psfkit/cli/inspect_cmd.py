"""``psfkit info``: validate a PSF-grid folder and summarise it."""

from __future__ import annotations

import argparse

import numpy as np

from psfkit.cli.help_all import add_command
from psfkit.cli.options import STRICT_HELP
from psfkit.io import read_grid
from psfkit.io.grid import IRREGULAR


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "info", "validate a PSF grid and print a summary", """
        Read and validate a PSF-grid folder (manifest and every image) and print what it
        holds.""", advanced=False)
    p.add_argument("grid", help="PSF-grid folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--strict", action="store_true", help=STRICT_HELP)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    grid = read_grid(args.grid, progress=not args.quiet, strict=args.strict)
    c, h, w = grid.image_shape
    print(f"grid:      {grid.root}")
    if grid.layout == IRREGULAR:
        print(f"layout:    irregular scan ({len(grid.positions)} positions located by their "
              "field coordinates, no grid indices)")
    else:
        missing = grid.missing()
        print(f"layout:    {grid.layout}"
              + (f" ({len(missing)} of {grid.grid_shape[0] * grid.grid_shape[1]} positions "
                 "not captured: " + ", ".join(f"({r}, {c})" for r, c in missing[:8])
                 + (" ..." if len(missing) > 8 else "") + ")" if missing else ""))
    shape = f"{grid.grid_shape[0]} x {grid.grid_shape[1]}" if grid.layout != IRREGULAR \
        else "scan"
    print(f"positions: {shape} ({len(grid.positions)} images, manifest {grid.manifest_name})")
    print(f"images:    {h} x {w} x {c} ({'/'.join(grid.channels)}), {grid.dtype}"
          + (f", {grid.bit_depth}-bit data" if grid.bit_depth else ""))
    centre = grid.center_index
    print(f"centre:    {grid.describe_index(centre) if centre else 'none'}"
          + ("" if centre is None or grid.has(*centre) else " (not captured: use --reference)"))
    fields = grid.field_deg()
    if fields is not None:
        print(f"field:     x {np.nanmin(fields[..., 0]):+.2f}..{np.nanmax(fields[..., 0]):+.2f} "
              f"deg, y {np.nanmin(fields[..., 1]):+.2f}..{np.nanmax(fields[..., 1]):+.2f} deg")
    exposures = grid.exposures()
    if exposures is not None:
        print(f"exposure:  {np.nanmin(exposures):g}..{np.nanmax(exposures):g} s")
    print(f"dark:      {grid.dark_file or 'none'}"
          + (f", black level {grid.black_level:g}" if grid.black_level is not None else ""))
    for file, problem in grid.frame_problems.items():
        print(f"flagged:   {file}: {problem.split(': ', 1)[-1]} (the analyses exclude it)")
    return 0
