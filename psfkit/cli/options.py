"""Command-line options shared by the commands that read a PSF grid."""

from __future__ import annotations

import argparse

from psfkit.preprocess import PreprocessOptions
from psfkit.validation import flag


def add_grid_options(p: argparse.ArgumentParser) -> None:
    """The grid argument and the preprocessing / registration options."""
    p.add_argument("grid", help="PSF-grid folder (manifest.json or manifest.csv + images)")
    g = p.add_argument_group("preprocessing")
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
    g.add_argument("--upsample", type=flag("--upsample"), default=100,
                   help="registration precision is 1/UPSAMPLE px (default 100)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def preprocess_options(args: argparse.Namespace) -> PreprocessOptions:
    return PreprocessOptions(normalization=args.normalization,
                             hot_pixel_sigma=args.hot_pixel_sigma,
                             saturation_level=args.saturation_level,
                             allow_saturated=args.allow_saturated)
