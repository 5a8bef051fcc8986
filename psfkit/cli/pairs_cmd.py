"""``psfkit fit-pairs`` and ``psfkit eval-model``: forward models from (scene, measurement)
pairs, and their prediction error on pairs they never saw."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.cli.help_all import add_help_all, mark_advanced
from psfkit.cli.run_file import add_config_option, run_file_record
from psfkit.cli.vocabulary import BASIS_ALIASES, add_flag, add_retired, command_name
from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.fitting.pairs.options import PairFitOptions
from psfkit.forward.kernelfile import load_kernels, save_kernels
from psfkit.forward.weights import BASIS_NAMES
from psfkit.forward.zones import ZONE_NAMES
from psfkit.io import OutputTransaction, read_pairs
from psfkit.io.flag_ranges import flag
from psfkit.io.json_documents import dumps_finite
from psfkit.io.jsonable import jsonable
from psfkit.io.pairs import parse_names
from psfkit.io.read_options import ReadOptions, choose
from psfkit.io.validation import require_finite

#: Flags that only ``--help-all`` lists (issue 44): the solver and the constraints, whose
#: defaults are chosen by held-out error or are a measured PSF's; the channel order, which the
#: pairs folder declares.
FIT_PAIRS_ADVANCED = ("--channel-order", "--tikhonov", "--difference", "--iterations",
                      "--no-scale", "--nonneg", "--support", "--support-threshold",
                      "--support-mask", "--projected-iterations", "--leave-one-out")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit-pairs", help="fit a shift-invariant or eigen-kernel model to image pairs",
        description="Regularised least-squares fit of the forward model y = crop(K * pad(x)) "
                    "(one PSF, or eigen-kernels with weight maps) to (scene, measurement) "
                    "pairs, by preconditioned conjugate gradients on the normal equations, "
                    "with the regularisation chosen by held-out error (cross-validation over "
                    "the pairs), then (by default) projected Newton under the constraints "
                    "of a measured PSF: non-negative, optionally zero outside a support. "
                    "Writes a kernel file that ekdun and eval-model read; its provenance "
                    "records the regularisation chosen, the constraints and support. "
                    "--help-all lists the advanced flags.")
    add_help_all(p)
    p.add_argument("pairs", help="pairs folder (scene/ + measurement/, or the DLMD layout "
                                 "lensed/ + diffuser/)")
    add_flag(p, "--basis", "fit-pairs",
             note=f"si; one of ek, {', '.join(BASIS_NAMES)}")
    add_flag(p, "--convention", "fit-pairs",
             note="sensor: K FFT pairs per iteration; source costs one FFT pair per "
                  "iteration and predicts held-out real pairs better (docs/your-camera.md)")
    p.add_argument("--out", required=True, help="kernel file to write (.npz)")
    _add_channel_order(p, "the folder's (pairs.json; BGR for the DLMD layout lensed/ + "
                          "diffuser/), else RGB; recorded in the kernel file")
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

    e = sub.add_parser(
        "eval-model", help="prediction error of kernel files on image pairs, over the field",
        description="Predict every measurement of a pairs folder from its scene with the "
                    "model of each kernel file and print ||y - A x|| / ||y|| per pair, raw "
                    "and with the best per-pair scale (for per-image normalised datasets), "
                    "whether the model was fitted on the pair or it was held out (the kernel "
                    "file's record), and the scaled error in three equal-area radial zones "
                    "of the sensor (centre, middle, edge). Give SI and EK files together to "
                    "compare them.")
    e.add_argument("models", nargs="+", metavar="MODEL",
                   help="kernel file(s) (.npz) from fit-pairs or fit-eigen, of one sensor")
    e.add_argument("pairs", help="pairs folder")
    e.add_argument("--downsample", type=flag("--downsample"), default=None, metavar="N",
                   help="bin the pairs N x N first (default: the factor the model was "
                        "fitted with, from its provenance, else 1)")
    _add_channel_order(e, "the folder's (pairs.json, DLMD layout), else the one recorded "
                          "in the kernel file, else RGB")
    add_flag(e, "--holdout", "eval-model", action="append",
             note="the kernel file's record of the pairs it was fitted on; without one, "
                  "every pair is held out")
    e.add_argument("--out", metavar="JSON",
                   help="write the errors to this JSON file, and beside it STEM_residual.npz "
                        "(per-pixel residual maps, on the held-out pairs where there are "
                        "any) and STEM_residual.png (the maps side by side, one colour scale)")
    e.add_argument("--overwrite", action="store_true", help="replace existing --out files")
    e.set_defaults(func=run_eval_model)


def _add_channel_order(p: argparse.ArgumentParser, default: str) -> None:
    add_flag(p, "--channel-order", command_name(p), note=default)


def _add_fit_options(p: argparse.ArgumentParser) -> None:
    d = PairFitOptions()
    g = p.add_argument_group("solver")
    g.add_argument("--downsample", type=flag("--downsample"), default=None, metavar="N",
                   help="bin scenes and measurements N x N before fitting (default 1)")
    g.add_argument("--tikhonov", type=flag("--tikhonov"), default=d.tikhonov,
                   help="ridge weight relative to the mean scene power (default: chosen by "
                        "held-out error for --basis si, 0 for eigen-kernels)")
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


def _refuse_blank(pairs: Any, scenes: np.ndarray, measurements: np.ndarray) -> None:
    """An all-zero scene or measurement carries no information and makes the per-pair scale
    0/0: name the file instead of reporting NaN kernels or errors later. Measurements whose
    light is out of all proportion to their scenes' would need kernels no kernel file may hold
    (``MIN_KERNEL_GAIN`` … ``MAX_KERNEL_GAIN``): the folder is named, not the model."""
    from psfkit.io.validation import MAX_KERNEL_GAIN, MIN_KERNEL_GAIN

    for stack, folder, files in ((scenes, pairs.scene_dir, pairs.scene_files),
                                 (measurements, pairs.measurement_dir, pairs.measurement_files)):
        blank = [i for i in range(len(stack)) if not np.any(stack[i])]
        if blank:
            raise InvalidInputError(f"{pairs.root / folder / files[blank[0]]}: all-zero image "
                                    "(nothing to fit or predict)")
    # a PSF's kernels sum to about the light a measurement holds per unit of scene light
    ratio = float(np.abs(measurements).sum(dtype=np.float64)
                  / np.abs(scenes).sum(dtype=np.float64))
    if not MIN_KERNEL_GAIN <= ratio <= MAX_KERNEL_GAIN:
        raise InvalidInputError(f"{pairs.root}: the measurements hold {ratio:.3g} times the "
                                "light of their scenes, beyond what kernels may sum to "
                                f"({MIN_KERNEL_GAIN:g} to {MAX_KERNEL_GAIN:g}); check the "
                                "units of the files (full scale is 1)")


def _load(folder: str, factor: int, channel_order: str | None = None,
          recorded: ReadOptions | None = None, holdout: list[str] | None = None
          ) -> tuple[Any, np.ndarray, np.ndarray]:
    """The pairs of ``folder`` (less those ``holdout`` names), binned ``factor`` times."""
    from psfkit.fitting.pairs.fit import downsample_pairs

    if factor < 1:
        raise InvalidInputError(f"--downsample must be >= 1, got {factor}")
    # load_all() checks every pair
    pairs = read_pairs(folder, channel_order, check_pixels=False, recorded=recorded)
    if holdout:
        pairs = pairs.subset(pairs.select(holdout))
    scenes, measurements = pairs.load_all()
    _refuse_blank(pairs, scenes, measurements)
    scenes, measurements = downsample_pairs(scenes, measurements, factor, str(folder))
    return pairs, scenes, measurements


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

    pairs, scenes, measurements = _load(args.pairs, args.downsample, args.channel_order,
                                        holdout=args.holdout)
    held = list(parse_names(args.holdout))
    mask = _support_mask(args.support_mask, args.downsample, scenes.shape[-2:])
    fit = fit_pairs(scenes, measurements, options, progress=not args.quiet,
                    support_mask=mask)
    physics = fit.physics()
    summary: dict[str, Any] = {
        "pairs": str(pairs.root), "names": list(pairs.names), "holdout": held, "model": basis,
        "convention": options.convention, "downsample": args.downsample,
        "sensor_shape": list(scenes.shape[-2:]), "options": options.__dict__,
        "training_error": dict(zip(pairs.names, fit.training_error.tolist(), strict=True)),
        "scales": dict(zip(pairs.names, fit.scales.tolist(), strict=True)),
        "solver": fit.history, "physics": physics}
    regularisation = fit.regularisation_record()
    summary["regularisation"] = regularisation
    if args.leave_one_out:
        # each fold fitted with the weights chosen on all the pairs (choosing them again in
        # every fold would nest one cross-validation in another)
        summary["leave_one_out"] = leave_one_out(
            scenes, measurements, dataclasses.replace(options, **fit.weights),
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
    if args.leave_one_out:
        loo = summary["leave_one_out"]
        print(f"  leave-one-out relative error: mean {loo['mean_raw']:.4f} raw, "
              f"{loo['mean_scaled']:.4f} with the best per-pair scale")


def run_eval_model(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else None
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        files = None
        if out is not None:
            stem = out.with_suffix("")
            files = (outputs.file(out), outputs.file(f"{stem}_residual.npz"),
                     outputs.file(f"{stem}_residual.png"))
        results, maps, zones, notices = _evaluate_all(args)
        document = _document(results)
        if files is not None:
            _write_eval(files, document, maps, zones, results, args.out)
    for result in results:
        _print_eval(result)
    if out is not None:
        stem = out.with_suffix("")
        print(f"wrote {out}, {stem}_residual.npz, {stem}_residual.png")
    for text in notices:   # after the work: an error stays the one line on stderr
        print(text, file=sys.stderr)
    return 0


def _document(results: list[dict[str, Any]]) -> dict[str, Any]:
    """The ``--out`` JSON: one model's result as it is, several as ``{"models": [...]}``."""
    if len(results) == 1:
        return results[0]
    return {"pairs": results[0]["pairs"], "models": results}


def _write_eval(files: tuple[Path, Path, Path], document: dict[str, Any],
                maps: list[np.ndarray], zones: Any, results: list[dict[str, Any]],
                name: str) -> None:
    from psfkit.report.figures.field import figure_residual_maps
    from psfkit.report.figures.style import publication_style

    json_file, npz_file, png_file = files
    json_file.write_text(dumps_finite(document, name, indent=1) + "\n", encoding="utf-8")
    np.savez_compressed(npz_file, maps=np.stack(maps), zones=zones.labels,
                        models=np.array([r["model"] for r in results]))
    titles = [f"{Path(r['model']).name}: {r['basis']}, {r['convention']}"
              f"\n{r['residual_map']['label']}" for r in results]
    figure = figure_residual_maps(maps, titles, zones)
    with publication_style():
        figure.savefig(png_file, format="png")


def _print_eval(result: dict[str, Any]) -> None:
    """One model's table: per pair, its role, raw and scaled errors and the scaled error by
    zone; then the means of the held-out and the fitted pairs."""
    print(f"{result['model']} ({result['basis']}, {result['convention']} weights): "
          f"{result['fit_record']}")
    print(f"{'pair':>16s}  {'role':8s}  {'raw':>8s}  {'scaled':>8s}   scaled by zone: "
          f"{'centre':>7s} {'middle':>7s} {'edge':>7s}")

    def row(label: str, role: str, entry: dict[str, Any]) -> None:
        values = [entry["by_zone"][z]["scaled"] for z in ZONE_NAMES]
        zones = " ".join("    n/a" if v is None else f"{v:7.4f}" for v in values)
        print(f"{label:>16s}  {role:8s}  {entry['raw']:8.4f}  {entry['scaled']:8.4f}   "
              f"{'':15s} {zones}")

    for name, entry in result["per_pair"].items():
        row(name, entry["role"], entry)
    for role in ("held_out", "fitted"):
        group = result[role]
        if group is not None:
            count = group["pairs_count"]
            row(f"mean {role.replace('_', ' ')}", f"{count} pair{'s' if count > 1 else ''}",
                {"raw": group["mean_raw"], "scaled": group["mean_scaled"],
                 "by_zone": group["by_zone"]})
    print(f"{'mean':>16s}  {'all':8s}  {result['mean_raw']:8.4f}  {result['mean_scaled']:8.4f}")


def _evaluate_all(args: argparse.Namespace
                  ) -> tuple[list[dict[str, Any]], list[np.ndarray], Any, list[str]]:
    """Every model of ``args.models`` on the pairs (read once per way of reading them)."""
    from psfkit.forward.zones import field_zones

    loaded: dict[Any, tuple[Any, np.ndarray, np.ndarray]] = {}
    results, maps, notices, zones = [], [], [], None
    for path in args.models:
        model = load_kernels(path)
        recorded = model.data_read_options()
        factor, notice = choose(args.downsample, recorded.downsample, 1, "--downsample", path)
        notices += [text for text in (notice, choose(args.channel_order,
                                                     recorded.channel_order, "RGB",
                                                     "--channel-order", path)[1]) if text]
        key = (factor, args.channel_order, tuple(sorted(recorded.to_json().items())))
        if key not in loaded:
            loaded[key] = _load(args.pairs, factor, args.channel_order, recorded)
        pairs, scenes, measurements = loaded[key]
        if tuple(scenes.shape[-2:]) != tuple(model.sensor_shape):
            raise InvalidInputError(
                f"{args.pairs}: pairs are {scenes.shape[-2]}x{scenes.shape[-1]} (after "
                f"--downsample {factor}) but the model {path} has a "
                f"{model.sensor_shape[0]}x{model.sensor_shape[1]} sensor")
        if zones is None:
            zones = field_zones(model.sensor_shape, model.optical_center)
        elif zones.shape != tuple(model.sensor_shape):
            raise InvalidInputError(f"{path}: its sensor is {model.sensor_shape[0]}x"
                                    f"{model.sensor_shape[1]}, {args.models[0]}'s "
                                    f"{zones.shape[0]}x{zones.shape[1]}; compare models of "
                                    "one sensor")
        result, residual = _evaluate(path, model, pairs, scenes, measurements, factor,
                                     args.holdout, zones)
        results.append(result)
        maps.append(residual)
    return results, maps, zones, list(dict.fromkeys(notices))


def _mean(values: np.ndarray) -> float | None:
    """Mean of the finite values (``None`` if none: a zone where every measurement is 0)."""
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else None


def _zone_summary(by_zone: dict[str, np.ndarray], rows: np.ndarray
                  ) -> dict[str, dict[str, float | None]]:
    """``{zone: {raw, scaled}}``: the mean over the pairs ``rows`` of each zone's errors."""
    return {z: {kind: _mean(by_zone[kind][rows, i]) for kind in ("raw", "scaled")}
            for i, z in enumerate(ZONE_NAMES)}


def _role_group(role: str, roles: tuple[str, ...], names: tuple[str, ...],
                errors: dict[str, np.ndarray], by_zone: dict[str, np.ndarray]
                ) -> dict[str, Any] | None:
    """The pairs of one role (fitted or held out) and their mean errors, whole and by zone;
    ``None`` when there is no such pair."""
    rows = np.array([r == role for r in roles])
    if not rows.any():
        return None
    return {"pairs": [n for n, r in zip(names, roles, strict=True) if r == role],
            "pairs_count": int(rows.sum()),
            "mean_raw": float(errors["raw"][rows].mean()),
            "mean_scaled": float(errors["scaled"][rows].mean()),
            "by_zone": _zone_summary(by_zone, rows)}


def _evaluate(path: str, model: Any, pairs: Any, scenes: np.ndarray,
              measurements: np.ndarray, factor: int, holdout: list[str] | None,
              zones: Any) -> tuple[dict[str, Any], np.ndarray]:
    """One model's errors (whole sensor, by zone, held-out and fitted pairs) and its residual
    map (over the held-out pairs where there are any, else over all)."""
    from psfkit.fitting.pairs.fit import predict, relative_errors
    from psfkit.fitting.pairs.model_errors import (
        FITTED,
        HELD_OUT,
        pair_roles,
        residual_map,
        zone_errors,
    )

    roles = pair_roles(model.provenance, pairs.root, pairs.names, holdout or (), path)
    prediction = predict(model, scenes, model_name=str(path), scenes_name=str(pairs.root))
    errors = relative_errors(prediction, measurements)
    by_zone = zone_errors(prediction, measurements, zones, errors["scale"])
    held = np.array([r == HELD_OUT for r in roles])
    on = held if held.any() else np.ones(len(roles), dtype=bool)
    residual = residual_map(prediction[on], measurements[on], errors["scale"][on])
    count = int(on.sum())
    per_pair = {name: {"raw": float(errors["raw"][i]), "scaled": float(errors["scaled"][i]),
                       "best_scale": float(errors["scale"][i]), "role": roles[i],
                       "by_zone": _zone_summary(by_zone, np.arange(len(roles)) == i)}
                for i, name in enumerate(pairs.names)}
    result = {"model": str(path), "pairs": str(pairs.root), "downsample": factor,
              "basis": model.basis, "convention": model.convention,
              "fit_record": f"fitted on {len(roles) - int(held.sum())} of these pairs, "
                            f"{int(held.sum())} held out",
              "per_pair": per_pair,
              "mean_raw": float(errors["raw"].mean()),
              "mean_scaled": float(errors["scaled"].mean()),
              "by_zone": _zone_summary(by_zone, np.ones(len(roles), dtype=bool)),
              "held_out": _role_group(HELD_OUT, roles, pairs.names, errors, by_zone),
              "fitted": _role_group(FITTED, roles, pairs.names, errors, by_zone),
              "zones": zones.describe(),
              "residual_map": {
                  "pairs": [n for n, k in zip(pairs.names, on, strict=True) if k],
                  "label": f"{count} {'held-out ' if held.any() else ''}"
                           f"pair{'s' if count > 1 else ''}",
                  # the map's RMS in each zone: where the residual is, in the units of the
                  # map (not relative to each zone's own signal)
                  "by_zone": {z: float(np.sqrt(np.mean(
                      residual[zones.labels == i].astype(np.float64) ** 2)))
                      for i, z in enumerate(ZONE_NAMES)},
                  "definition": "per-pixel RMS over pairs and channels of the residual with "
                                "the best per-pair scale, divided by the RMS of those pairs' "
                                "measurements"}}
    return result, residual
