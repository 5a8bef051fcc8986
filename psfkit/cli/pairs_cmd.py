"""``psfkit fit-pairs``: forward models from (scene, measurement) pairs (their prediction
error on pairs they never saw: :mod:`psfkit.cli.eval_cmd`)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.cli.help_all import add_command, mark_advanced
from psfkit.cli.pairs_folder import load_pairs
from psfkit.cli.run_file import add_config_option, run_file_record
from psfkit.cli.vocabulary import BASIS_ALIASES, add_flag, add_retired
from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.fitting.pairs.options import PairFitOptions
from psfkit.forward.kernelfile import save_kernels
from psfkit.forward.weights import BASIS_NAMES
from psfkit.io import OutputTransaction
from psfkit.io.flag_ranges import flag
from psfkit.io.json_documents import dumps_finite
from psfkit.io.jsonable import jsonable
from psfkit.io.pairs import parse_names
from psfkit.io.validation import require_finite

#: Flags that only ``--help-all`` lists: the solver and the constraints, whose
#: defaults are chosen by held-out error or are a measured PSF's; the channel order, which the
#: pairs folder declares.
FIT_PAIRS_ADVANCED = ("--channel-order", "--tikhonov", "--difference", "--iterations",
                      "--no-scale", "--nonneg", "--support", "--support-threshold",
                      "--support-mask", "--projected-iterations", "--leave-one-out")


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "fit-pairs",
                    "fit a shift-invariant or eigen-kernel model to image pairs", """
        Regularised least-squares fit of the forward model y = crop(K * pad(x)) (one PSF, or
        eigen-kernels with weight maps) to (scene, measurement) pairs, by preconditioned
        conjugate gradients on the normal equations, with the regularisation chosen by held-out
        error (cross-validation over the pairs), then (by default) projected Newton under the
        constraints of a measured PSF: non-negative, optionally zero outside a support. Writes
        a kernel file that ekdun and eval-model read; its provenance records the regularisation
        chosen, the constraints and support.""")
    p.add_argument("pairs", help="pairs folder (scene/ + measurement/, or the DLMD layout "
                                 "lensed/ + diffuser/)")
    add_flag(p, "--basis", "fit-pairs",
             note=f"si; one of ek, {', '.join(BASIS_NAMES)}")
    add_flag(p, "--convention", "fit-pairs",
             note="auto: each convention at its own chosen regularisation on the same folds, "
                  "the source side unless the sensor side predicts the held-out pairs "
                  "better by more than a standard error; the kernel file records the "
                  "choice")
    p.add_argument("--out", required=True, help="kernel file to write (.npz)")
    add_flag(p, "--channel-order", "fit-pairs",
             note="the folder's (pairs.json; BGR for the DLMD layout lensed/ + diffuser/), "
                  "else RGB; recorded in the kernel file")
    _add_fit_options(p)
    add_flag(p, "--holdout", "fit-pairs", action="append",
             note="none; the kernel file records the fitted and the held-out names, and "
                  "eval-model reports the two apart")
    p.add_argument("--leave-one-out", action="store_true",
                   help="also report each pair's error when it is left out of the fit")
    p.add_argument("--report", metavar="JSON", help="write the fit summary to this JSON file")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out or --report file")
    add_config_option(p, "tikhonov = 1e-3", "the kernel file's provenance")
    add_retired(p, "fit-pairs")
    mark_advanced(p, FIT_PAIRS_ADVANCED)
    p.set_defaults(func=run_fit_pairs)


def _add_fit_options(p: argparse.ArgumentParser) -> None:
    d = PairFitOptions()
    g = p.add_argument_group("solver")
    g.add_argument("--downsample", type=flag("--downsample"), default=None, metavar="N",
                   help="bin scenes and measurements N x N before fitting (default 1)")
    g.add_argument("--tikhonov", type=flag("--tikhonov"), default=d.tikhonov,
                   help="ridge weight relative to the mean scene power (default: chosen by "
                        "held-out error; for eigen-kernels at most 0.01, after --difference)")
    g.add_argument("--difference", type=flag("--difference"), default=d.difference,
                   help="pull of the correction kernels towards the base kernel, relative "
                        "likewise (default: chosen by held-out error; eigen-kernels only)")
    g.add_argument("--iterations", type=flag("--iterations"), default=None,
                   help="most conjugate-gradient iterations of the final solve, which "
                        f"stops at a relative residual of {d.tolerance:g} (default "
                        f"{d.final_iterations})")
    g.add_argument("--no-scale", action="store_true",
                   help="do not estimate a scale per pair (use when the pairs share one "
                        "exposure and normalisation)")
    c = p.add_argument_group("constraints (a measured PSF's)")
    c.add_argument("--nonneg", action=argparse.BooleanOptionalAction, default=d.nonneg,
                   help="non-negative kernels (default); --no-nonneg gives the unconstrained "
                        "least-squares kernels, with their negative lobes")
    c.add_argument("--support", choices=("none", "auto"), default="none",
                   help="auto: kernels are zero outside the caustic footprint of the "
                        "unconstrained base kernel (smoothed |K| above --support-threshold of "
                        "its maximum, dilated 2 pixels); default none")
    c.add_argument("--support-threshold", type=flag("--support-threshold"), default=None,
                   help=f"fraction of the maximum for --support auto (default "
                        f"{d.support_threshold:g}; refused without --support auto)")
    c.add_argument("--support-mask", metavar="FILE",
                   help="footprint image (.npy/.png/.tif, nonzero = inside) of the sensor's "
                        "size, binned by --downsample; overrides --support")
    c.add_argument("--projected-iterations", type=flag("--projected-iterations"), default=None,
                   help="most projected Newton steps of the non-negative solve (default "
                        "100)")


def _support_mask(path: str | None, factor: int, shape: tuple[int, int]) -> np.ndarray | None:
    """The ``--support-mask`` image as a ``shape`` bool array: a pixel of the binned grid is
    inside when any of its ``factor × factor`` sensor pixels is."""
    if path is None:
        return None
    from psfkit.io.images import read_image
    from psfkit.numerics.resample import bin_mean

    image = require_finite(read_image(path), str(path))
    mask = image.astype(np.float64).max(axis=0) != 0
    if not mask.any():   # would constrain every kernel to zero
        raise InvalidInputError(f"{path}: the support mask is empty (no nonzero pixel)")
    if factor > 1 and mask.shape[0] >= shape[0] * factor and mask.shape[1] >= shape[1] * factor:
        mask = bin_mean(mask.astype(np.float32), factor) > 0
    if tuple(mask.shape) != tuple(shape):
        raise InvalidInputError(f"{path}: the support mask is {mask.shape[0]}x{mask.shape[1]}, "
                                f"the fitted sensor {shape[0]}x{shape[1]} (after --downsample "
                                f"{factor})")
    return mask


def run_fit_pairs(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix != ".npz":
        raise InvalidInputError(f"{out}: kernel files are .npz")
    args.downsample = args.downsample or 1
    basis = BASIS_ALIASES.get(args.basis, args.basis)
    if args.support_threshold is not None and (args.support != "auto" or args.support_mask):
        raise ConfigurationError("--support-threshold acts only with --support auto (and no "
                                 "--support-mask)")
    threshold = (PairFitOptions.support_threshold if args.support_threshold is None
                 else args.support_threshold)
    options = PairFitOptions(basis=basis, convention=args.convention, tikhonov=args.tikhonov,
                             difference=args.difference, iterations=args.iterations,
                             fit_scale=not args.no_scale, nonneg=args.nonneg,
                             support="mask" if args.support_mask else args.support,
                             support_threshold=threshold,
                             projected_iterations=args.projected_iterations)
    # both outputs are checked before the fit and appear together, or neither does
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        kernels = outputs.file(out)
        report = outputs.file(args.report) if args.report else None
        pairs, scenes, fit, summary = _fit(args, basis, options, kernels, report)
    _print_fit(args, basis, out, pairs, scenes, fit, summary)
    return 0


def _fit(args: argparse.Namespace, basis: str, options: PairFitOptions, kernels: Path,
         report: Path | None) -> tuple[Any, np.ndarray, Any, dict[str, Any]]:
    """Fit, and write the kernel file (and report) to the given temporary paths."""
    # torch is imported here, by the commands that use it, not when the parser is built
    from psfkit.fitting.pairs.fit import fit_pairs, leave_one_out

    pairs, scenes, measurements = load_pairs(args.pairs, args.downsample, args.channel_order,
                                             holdout=args.holdout)
    held = list(parse_names(args.holdout))
    mask = _support_mask(args.support_mask, args.downsample, scenes.shape[-2:])
    fit = fit_pairs(scenes, measurements, options, progress=not args.quiet,
                    support_mask=mask)
    physics = fit.physics()
    summary: dict[str, Any] = {
        "pairs": str(pairs.root), "names": list(pairs.names), "holdout": held, "model": basis,
        "convention": fit.convention, "downsample": args.downsample,
        "sensor_shape": list(scenes.shape[-2:]), "options": options.__dict__,
        "training_error": dict(zip(pairs.names, fit.training_error.tolist(), strict=True)),
        "scales": dict(zip(pairs.names, fit.scales.tolist(), strict=True)),
        "solver": fit.history, "physics": physics,
        "regularisation": fit.regularisation_record()}
    if fit.convention_choice:
        summary["convention_choice"] = fit.convention_choice
    if args.leave_one_out:
        # each fold fitted with the weights chosen on all the pairs (choosing them again in
        # every fold would nest one cross-validation in another)
        summary["leave_one_out"] = leave_one_out(
            scenes, measurements,
            dataclasses.replace(options, convention=fit.convention, **fit.weights),
            progress=not args.quiet, support_mask=mask)
    # the folder (resolved: eval-model compares it with the folder it is given) and the
    # names fitted on; "holdout" only where pairs were held out (files without it held none)
    provenance = {"source": "psfkit fit-pairs", "pairs": str(pairs.root.resolve()),
                  "names": list(pairs.names), **({"holdout": held} if held else {}),
                  "downsample": args.downsample,
                  "options": options.__dict__, "training_error":
                  [round(float(e), 6) for e in fit.training_error], "physics": physics}
    if args.support_mask:
        provenance["support_mask"] = str(args.support_mask)
    if run_file_record(args) is not None:   # the settings of --config, with the file's path
        provenance["run_file"] = summary["run_file"] = run_file_record(args)
    save_kernels(kernels, fit.kernel_model(provenance, pairs.read_options(args.downsample)))
    if report is not None:
        report.write_text(dumps_finite(jsonable(summary), args.report, indent=1) + "\n",
                          encoding="utf-8")
    return pairs, scenes, fit, summary


def _print_fit(args: argparse.Namespace, basis: str, out: Path, pairs: Any,
               scenes: np.ndarray, fit: Any, summary: dict[str, Any]) -> None:
    name = "shift-invariant PSF" if basis == "si" else f"{basis} eigen-kernels"
    print(f"fitted a {name} to {len(pairs)} pairs of {scenes.shape[-2]}x{scenes.shape[-1]}x"
          f"{scenes.shape[1]}; wrote {out}")
    if summary["holdout"]:
        print(f"  held out (not fitted; recorded in {out.name}): "
              f"{', '.join(summary['holdout'])}")
    print(f"  training relative error: mean {fit.training_error.mean():.4f}, "
          f"max {fit.training_error.max():.4f}"
          + ("" if args.no_scale else f" (per-pair scales {fit.scales.min():.3f}-"
                                      f"{fit.scales.max():.3f})"))
    options, physics = fit.options, summary["physics"]
    constraints = [name for name, on in (("non-negative", options.nonneg),
                                         (f"support {options.support}",
                                          options.support != "none")) if on]
    print(f"  kernels: {', '.join(constraints) or 'unconstrained'}; "
          f"{physics['negative_pixels']} negative pixels, support fraction "
          f"{physics['support_fraction']:.3f}")
    if options.nonneg:
        step = fit.history[-1]
        print(f"  non-negative least squares: {step['iterations']} Newton steps, KKT residual "
              f"{step['kkt_residual']:.1e} ("
              + ("converged" if step["converged"] else
                 f"NOT converged: stopped at --projected-iterations "
                 f"{options.final_projected_iterations}") + ")")
    for choice in fit.regularisation:
        print(f"  {choice.summary()}")
    if fit.convention_choice:
        from psfkit.fitting.pairs.regularisation import convention_summary

        print(f"  {convention_summary(fit.convention_choice)}")
    if args.leave_one_out:
        loo = summary["leave_one_out"]
        print(f"  leave-one-out relative error: mean {loo['mean_raw']:.4f} raw, "
              f"{loo['mean_scaled']:.4f} with the best per-pair scale")
