"""``psfkit fit-eigen``: eigen-kernel forward models from a measured PSF grid."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psfkit.choices import CV_BASES, CV_BASES_ALL, SHIFT_MODES
from psfkit.cli.help_all import add_command, mark_advanced
from psfkit.cli.options import (
    add_grid_options,
    open_grid,
    preprocess_options,
    print_coverage,
)
from psfkit.cli.run_file import add_config_option, run_file_record
from psfkit.cli.summaries import pm, print_verdict
from psfkit.cli.vocabulary import BASIS_ALIASES, add_flag
from psfkit.errors import InvalidInputError
from psfkit.forward.kernelfile import save_kernels
from psfkit.forward.weights import BASIS_NAMES
from psfkit.io import OutputTransaction, atomic_directory
from psfkit.io.flag_ranges import flag
from psfkit.io.jsonable import write_json

# The fit (scipy) and the figures (matplotlib) are imported by the command that runs them,
# not when the parser is built (``psfkit --help`` stays fast).
if TYPE_CHECKING:
    from psfkit.fitting.grid.options import EigenFitOptions
    from psfkit.fitting.grid.result import GridEigenResult


#: Flags that only ``--help-all`` lists: the preprocessing and registration settings
#: (``psfkit report`` shows the ones a grid needs first), the position placement and
#: the cross-validation, whose defaults the fit's own verdict checks.
FIT_EIGEN_ADVANCED = ("--normalization", "--saturation-level", "--allow-saturated",
                      "--hot-pixel-sigma", "--upsample", "--min-ncc", "--gain-compensate",
                      "--shifts", "--cv-bases", "--folds")


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "fit-eigen", "fit eigen-kernels (Kbase, Kv, Kh, ...) to a PSF grid", """
        Least-squares fit of the eigen-kernel model PSF = sum_k W_k K_k (paper Eq. 7) to the
        registered grid, with sensor-side and source-side weights, cross-validated against
        richer bases and compared with a PCA. Writes the kernel file that ekdun trains from.""")
    add_grid_options(p)
    p.add_argument("--out", required=True, help="kernel file to write (.npz)")
    add_flag(p, "--basis", "fit-eigen",
             note=f"paper; one of ek, {', '.join(BASIS_NAMES)}, or auto: the best "
                  "cross-validated one")
    add_flag(p, "--convention", "fit-eigen",
             note="sensor, or with --basis auto the verdict's; auto fits both and writes the "
                  "one with the lower cross-validated error")
    p.add_argument("--gain-compensate", action="store_true",
                   help="divide every PSF by its gain first (kernels then carry shape only)")
    p.add_argument("--shifts", choices=SHIFT_MODES, default="affine",
                   help="where each PSF is placed for the fit: affine = the affine field-to-"
                        "shift map of the reliably registered positions, the forward model's "
                        "geometry (distortion stays in the kernels); registered = each PSF's "
                        "own registered shift (default affine)")
    p.add_argument("--cv-bases", default=",".join(CV_BASES),
                   help=f"comma-separated bases compared by cross-validation with the fitted "
                        f"one (default {','.join(CV_BASES)}; 'all' = {','.join(CV_BASES_ALL)}; "
                        "'none' to skip)")
    p.add_argument("--folds", type=flag("--folds"), default=9,
                   help="cross-validation folds (default 9)")
    p.add_argument("--figures", metavar="DIR",
                   help="also write Fig. 7 (kernels), Fig. 3 (weights), diagnostics and a JSON "
                        "summary into DIR")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out file or --figures folder")
    add_config_option(p, "folds = 5", "the kernel file's provenance")
    mark_advanced(p, FIT_EIGEN_ADVANCED)
    p.set_defaults(func=run_fit_eigen)


def _options(args: argparse.Namespace, basis: str) -> EigenFitOptions:
    from psfkit.fitting.grid.options import EigenFitOptions

    choice = args.cv_bases.strip().lower()
    cv = () if choice == "none" else CV_BASES_ALL if choice == "all" else tuple(
        b.strip() for b in args.cv_bases.split(",") if b.strip())
    convention = args.convention or ("auto" if basis == "auto" else "sensor")
    return EigenFitOptions(basis=basis, convention=convention,
                           gain_compensate=args.gain_compensate,
                           cv_bases=cv, folds=args.folds, upsample=args.upsample,
                           preprocess=preprocess_options(args), min_quality=args.min_ncc,
                           strict=args.strict, shifts=args.shifts)


def write_fit_figures(result: GridEigenResult, folder: Path, overwrite: bool = False) -> None:
    """Fig. 7 (kernels, and zoomed), Fig. 3 (weight maps), diagnostics and ``fit.json`` of an
    eigen-kernel fit, written atomically into ``folder``."""
    from psfkit.report.figures import (
        difference_sizes,
        figure_eigen_diagnostics,
        figure_kernels,
        figure_weight_maps,
        save_figure,
    )

    model = result.kernel_model()
    with atomic_directory(folder, overwrite=overwrite) as tmp:
        names = list(model.kernel_names)
        sizes = difference_sizes(result, names)     # ±1σ and significance, where fitted
        save_figure(figure_kernels(model.kernels, names, "measured eigen-kernels", sizes=sizes),
                    tmp / "fig7_kernels")
        save_figure(figure_kernels(model.kernels, names, "measured eigen-kernels (zoom)",
                                   zoom=0.3, sizes=sizes), tmp / "fig7_kernels_zoom")
        save_figure(figure_weight_maps(model.basis, model.sensor_shape), tmp / "fig3_weights")
        save_figure(figure_eigen_diagnostics(result), tmp / "diagnostics")
        write_json(tmp / "fit.json", result.summary())


def run_fit_eigen(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix != ".npz":
        raise InvalidInputError(f"{out}: kernel files are .npz")
    # both outputs are checked before the fit and appear together, or neither does
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        figures = outputs.folder(args.figures) if args.figures else None
        kernels = outputs.file(out)
        result = _fit(args, figures, kernels)
    _print_summary(result, result.basis_name, out)
    return 0


def _fit(args: argparse.Namespace, figures: Path | None, kernels: Path) -> GridEigenResult:
    """Fit, and write the kernel file (and figures) to the given temporary paths."""
    from psfkit.fitting.grid.fit import fit_eigen_grid

    grid = open_grid(args)   # every image is checked as it is processed
    basis = BASIS_ALIASES.get(args.basis, args.basis)
    # --basis auto: the verdict chooses basis and convention inside the one fit (every basis
    # cross-validated there), from the same held-out comparison psfkit report states
    result = fit_eigen_grid(grid, _options(args, basis), progress=not args.quiet)
    if figures is not None:
        write_fit_figures(result, figures, overwrite=True)   # into the empty temporary folder
    model = result.kernel_model()
    record = run_file_record(args)
    if record is not None:   # the settings of --config, with the file's path
        model = dataclasses.replace(model, provenance={**model.provenance, "run_file": record})
    save_kernels(kernels, model)
    return result


#: Ratio of the brightest to the faintest PSF above which fit-eigen's errors carry a caveat
#: (vignetting over a wide field reaches about 2: cos⁴ of 35°).
BRIGHTNESS_SPREAD = 2.0


def _print_summary(result: GridEigenResult, basis: str, out: Path) -> None:
    model = result.kernel_model()
    grid_shape = result.grid_shape
    summary = result.summary()
    if result.layout == "full lattice" and not result.excluded:
        fitted = f"{grid_shape[0]}x{grid_shape[1]} PSFs"
    elif result.layout == "irregular":
        fitted = f"{result.n_positions} PSFs of an irregular scan"
    else:
        fitted = f"{result.n_positions} PSFs of the {grid_shape[0]}x{grid_shape[1]} " \
                 f"{result.layout}"
    print(f"fitted basis {basis!r} ({', '.join(model.kernel_names)}) to {fitted}; wrote "
          f"{out} ({model.convention}-side weights)")
    print_coverage(result)
    placement = result.placement
    if placement is None:
        print("  PSFs placed at their own registered shifts (--shifts registered)")
    elif placement.source.startswith("registered"):
        why = ("no two-dimensional field to fit a shift map to"
               if placement.source == "registered" else "the field-to-shift map does not "
               "explain them: cut-outs around each PSF?")
        print(f"  PSFs placed at their own registered shifts ({why})")
    else:
        which = "reliable" if placement.source == "affine" else "all"
        print(f"  PSFs placed by the affine shift map of {placement.positions_used} positions "
              f"({which}); registered shifts deviate from it by up to "
              f"{placement.deviation_px:.2f} px (kept in the kernels)")
    for conv, res in summary["in_sample_relative_error"].items():
        print(f"  {conv}-side weights: in-sample relative error median {res['median']:.4f}, "
              f"max {res['max']:.4f}")
    if result.cv is not None:
        print("  cross-validated (held-out positions) relative error"
              f"{_brightness_caveat(result)}:")
        sigmas = result.cv["held_out_sigma"]
        for name, err in result.cv["held_out_relative_error"].items():
            print(f"    {name:28s} {pm(err, sigmas[name])}")
    for name, estimate in result.kernel_differences().items():
        print(f"  {name}: {estimate.text('.3g')} of Kbase (relative norm, working copy)")
    _print_verdict_and_choice(result, basis)
    if result.angles_deg is not None:
        print("  principal angles eigen-kernels vs top PCA subspace (deg): "
              + ", ".join(f"{a:.1f}" for a in result.angles_deg))


def _brightness_caveat(result: GridEigenResult) -> str:
    """A caveat for the errors when the PSFs' light varies more than vignetting would (stars
    of different brightness) and the fit is not gain-compensated: the errors then measure the
    brightness ratios, not the PSFs' shapes (the verdict compares the shapes)."""
    gains = result.stack.gains[np.isfinite(result.stack.gains) & (result.stack.gains > 0)]
    if result.options.gain_compensate or gains.size < 2:
        return ""
    spread = float(gains.max() / gains.min())
    if spread < BRIGHTNESS_SPREAD:
        return ""
    return (f" (the PSFs' light varies {spread:.1f}x between positions and is part of these "
            "errors; --gain-compensate compares their shapes, as the verdict does)")


def _print_verdict_and_choice(result: GridEigenResult, basis: str) -> None:
    """The verdict, and one note when the written model is not the one it recommends (never
    with ``--basis auto``, which writes that model)."""
    verdict = result.verdict
    if verdict is None:
        return
    print_verdict(verdict)
    written = "si" if basis == "si" else f"{basis}/{result.convention}"
    if result.options.basis != "auto" and written != verdict.recommended_model:
        print(f"  note: the verdict recommends {verdict.recommended_model}, this file holds "
              f"{written}; rerun with --basis auto to write the recommended model")
