"""Command-line options shared by the commands that read a PSF grid."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from psfkit.calibration.preprocess import PreprocessOptions
from psfkit.io.flag_ranges import flag

if TYPE_CHECKING:
    from psfkit.io.grid import PsfGrid


#: ``--strict`` (``psfkit info`` and the commands that analyse a grid).
STRICT_HELP = ("all or nothing: refuse an incomplete lattice, an irregular scan and any "
               "unusable capture (saturated, no signal, NaN/Inf, failed registration) instead "
               "of excluding it with its reason")


def add_grid_options(p: argparse.ArgumentParser) -> None:
    """The grid argument, the preprocessing / registration options and how positions that
    fail a quality check, and the reference, are handled."""
    p.add_argument("grid", help="PSF-grid folder (manifest.json or manifest.csv + images)")
    g = add_preprocess_options(p, "preprocessing")
    g.add_argument("--upsample", type=flag("--upsample"), default=100,
                   help="registration precision is 1/UPSAMPLE px (default 100)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    g = p.add_argument_group("bad positions and the reference")
    g.add_argument("--strict", action="store_true", help=STRICT_HELP)
    g.add_argument("--reference", metavar="R,C",
                   help="compare every PSF with this position instead of the centre one: "
                        "grid row and column R,C, the I-th position of an irregular scan, or a "
                        "file name of the manifest")
    g.add_argument("--min-ncc", type=flag("--min-ncc"), default=0.5, metavar="NCC",
                   help="exclude positions whose registration quality (normalized "
                        "cross-correlation with the reference after alignment) is below NCC "
                        "(default 0.5)")


def add_preprocess_options(p: argparse.ArgumentParser, title: str) -> argparse._ArgumentGroup:
    """The options of :func:`preprocess_options`, in a group of that ``title`` (returned)."""
    g = p.add_argument_group(title)
    g.add_argument("--normalization", choices=("max", "sum"), default="max",
                   help="scale PSFs by the centre PSF's peak (max) or total (sum); "
                        "default max")
    g.add_argument("--saturation-level", type=flag("--saturation-level"), default=None,
                   metavar="VALUE",
                   help="raw value at which the sensor clips (default: from dtype/bit_depth)")
    g.add_argument("--allow-saturated", action="store_true",
                   help="mask heavily saturated PSFs instead of refusing them")
    g.add_argument("--hot-pixel-sigma", type=flag("--hot-pixel-sigma"), default=8.0,
                   help="dark-frame outlier threshold in robust std (default 8)")
    return g


def preprocess_options(args: argparse.Namespace) -> PreprocessOptions:
    return PreprocessOptions(normalization=args.normalization,
                             hot_pixel_sigma=args.hot_pixel_sigma,
                             saturation_level=args.saturation_level,
                             allow_saturated=args.allow_saturated)


def open_grid(args: argparse.Namespace) -> PsfGrid:
    """The grid of ``args.grid`` (pixels checked as each image is processed), with the
    ``--reference`` of the command line."""
    from psfkit.io import read_grid

    grid = read_grid(args.grid, check_pixels=False, strict=args.strict)
    if args.reference:
        grid = grid.with_reference(grid.find_reference(args.reference))
    return grid


def print_coverage(result: Any) -> None:
    """What was left out: cells never captured and positions excluded, with their reasons."""
    if result.missing:
        cells = ", ".join(f"({r}, {c})" for r, c in result.missing[:12])
        more = f" and {len(result.missing) - 12} more" if len(result.missing) > 12 else ""
        print(f"not captured: {len(result.missing)} position(s) of the "
              f"{result.grid_shape[0]}x{result.grid_shape[1]} lattice: {cells}{more}")
    if result.excluded:
        print(f"excluded: {len(result.excluded)} position(s) failed a quality check:")
        for e in result.excluded:
            where = f"#{e.col}" if result.layout == "irregular" else f"({e.row}, {e.col})"
            print(f"  {where} {e.file}: {e.reason} ({e.detail})")
