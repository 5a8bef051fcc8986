"""``psfkit eval-model``: the prediction error of kernel files on (scene, measurement) pairs,
per pair, held out or fitted, and over the field (three radial zones, a residual map)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.cli.help_all import add_command
from psfkit.cli.pairs_folder import load_pairs
from psfkit.cli.vocabulary import add_flag
from psfkit.errors import InvalidInputError
from psfkit.forward.kernelfile import load_kernels
from psfkit.forward.zones import ZONE_NAMES
from psfkit.io import OutputTransaction
from psfkit.io.flag_ranges import flag
from psfkit.io.json_documents import dumps_finite
from psfkit.io.read_options import choose


def register(sub: argparse._SubParsersAction) -> None:
    e = add_command(sub, "eval-model",
                    "prediction error of kernel files on image pairs, over the field", """
        Predict every measurement of a pairs folder from its scene with the model of each
        kernel file and print ||y - A x|| / ||y|| per pair, raw and with the best per-pair
        scale (for per-image normalised datasets), whether the model was fitted on the pair or
        it was held out (the kernel file's record), and the scaled error in three equal-area
        radial zones of the sensor (centre, middle, edge). Give SI and EK files together to
        compare them.""", advanced=False)
    e.add_argument("models", nargs="+", metavar="MODEL",
                   help="kernel file(s) (.npz) from fit-pairs or fit-eigen, of one sensor")
    e.add_argument("pairs", help="pairs folder")
    e.add_argument("--downsample", type=flag("--downsample"), default=None, metavar="N",
                   help="bin the pairs N x N first (default: the factor the model was "
                        "fitted with, from its provenance, else 1)")
    add_flag(e, "--channel-order", "eval-model",
             note="the folder's (pairs.json, DLMD layout), else the one recorded in the "
                  "kernel file, else RGB")
    add_flag(e, "--holdout", "eval-model", action="append",
             note="the kernel file's record of the pairs it was fitted on; without one, "
                  "every pair is held out")
    e.add_argument("--out", metavar="JSON",
                   help="write the errors to this JSON file, and beside it STEM_residual.npz "
                        "(per-pixel residual maps, on the held-out pairs where there are "
                        "any) and STEM_residual.png (the maps side by side, one colour scale)")
    e.add_argument("--overwrite", action="store_true", help="replace existing --out files")
    e.set_defaults(func=run_eval_model)


def run_eval_model(args: argparse.Namespace) -> int:
    stem = Path(args.out).with_suffix("") if args.out else None
    names = [str(Path(args.out)), f"{stem}_residual.npz", f"{stem}_residual.png"] if stem else []
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        files = [outputs.file(name) for name in names]
        results, maps, zones, notices = _evaluate_all(args)
        if files:   # one model's result as it is, several as {"models": [...]}
            document = results[0] if len(results) == 1 else {"pairs": results[0]["pairs"],
                                                             "models": results}
            _write_eval(files, document, maps, zones, results, args.out)
    for result in results:
        _print_eval(result)
    if names:
        print(f"wrote {', '.join(names)}")
    for text in notices:   # after the work: an error stays the one line on stderr
        print(text, file=sys.stderr)
    return 0


def _write_eval(files: list[Path], document: dict[str, Any],
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
    """One model's table of errors: per pair, then the means of each role."""
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
            loaded[key] = load_pairs(args.pairs, factor, args.channel_order, recorded)
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
    """The pairs of one role and their mean errors (``None`` when there is no such pair)."""
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
