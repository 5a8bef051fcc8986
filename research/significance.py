"""How often the significance rule calls an effect where there is none, how often it finds the
effects the default camera has, and whether the reported 1σ match the spread (issue 43).

Two virtual-bench cameras, each simulated once (5 × 5 grid at downsample 8 unless told
otherwise; the diffuser and the clean PSFs of seed 0), then captured again with ``--seeds``
independent noise draws (the sensor's Poisson–Gaussian noise on the same clean signal, so that
only the noise changes between runs):

- ``field_free``: ``BenchConfig(field_free=True)``, no field effect at all: every effect the
  rule calls, and every "shift-variant" verdict, is a false positive;
- ``default``: the default camera (vignetting cos⁴, astigmatism, PSF deformation).

Every run is characterized as ``psfkit report`` does (all steps, the verdict included). For
each fitted quantity the script keeps value, σ, z and p, and prints

- the false-positive rate on the field-free camera for several thresholds ``Z`` (the rule:
  ``z > Z`` and ``p < 2(1 − Φ(Z))``), per quantity and pooled;
- the detection rate on the default camera at the chosen ``Z``;
- the calibration of σ: the standard deviation of the value over the noise draws divided by
  the RMS of the reported σ (1 = calibrated), per camera and quantity.

Usage::

    python -m research.significance --seeds 12 --out bench_significance.json
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from psfkit.characterization.characterize import characterize_grid
from psfkit.io import read_grid
from psfkit.io.images import write_image
from psfkit.io.jsonable import write_json
from psfkit.numerics.significance import Z_SIGNIFICANT
from psfkit.simulate import BenchConfig, read_ground_truth, simulate_grid

THRESHOLDS = (2.0, 2.5, 3.0, 3.5, 4.0)


def recapture(clean_grid: Path, out: Path, seed: int) -> Path:
    """A copy of a simulated grid whose PSFs (and dark frame) are captured again from the
    ground truth's clean signal with the noise stream ``seed``."""
    truth = read_ground_truth(clean_grid)
    sensor = truth.config.sensor
    grid = read_grid(clean_grid)
    shutil.copytree(clean_grid, out)
    rng = np.random.default_rng([seed, 43])
    per_unit = sensor.electrons_per_dn / sensor.container_scale   # electrons per file unit
    for pos in grid.positions:
        electrons = np.asarray(truth.clean_psfs[pos.row, pos.col], np.float64) * per_unit
        write_image(out / pos.file, sensor.capture(electrons, rng))
    if grid.dark_file is not None:
        write_image(out / grid.dark_file,
                    sensor.capture(np.zeros((len(grid.channels), *grid.image_shape[1:])), rng))
    return out


def quantities(result: Any) -> dict[str, dict[str, Any]]:
    """Every fitted quantity of a characterization as ``Estimate.to_dict()``, and the
    verdict's field test."""
    out = {}
    if result.shift_fit is not None:
        for name, estimate in result.shift_fit.estimates.items():
            out[f"shift_map.{name}"] = estimate.to_dict()
    out["gain.cos_exponent"] = result.gain_fit.estimate.to_dict()
    effects = result.effects()
    out["warp.growth"] = effects["warp"].to_dict()
    out["astigmatism.tangential_sagittal"] = effects["astigmatism"].to_dict()
    test = result.verdict.field_test.to_dict()
    test["shift_variant"] = result.verdict.shift_variant
    test["recommended_model"] = result.verdict.recommended_model
    out["verdict.field_test"] = test
    return out


def significant_at(q: dict[str, Any], z_threshold: float) -> bool:
    """The rule at threshold ``z_threshold`` (the verdict's test: an improvement only)."""
    if q.get("z") is None or q.get("p_value") is None:
        return False
    if "shift_variant" in q and (q.get("value") or 0.0) <= 0:
        return False
    return q["z"] > z_threshold and q["p_value"] < 2 * stats.norm.sf(z_threshold)


def run(kind: str, seeds: int, downsample: int, shape: tuple[int, int], work: Path
        ) -> list[dict[str, Any]]:
    config = BenchConfig(downsample=downsample, field_free=kind == "field_free")
    clean = simulate_grid(work / f"{kind}_clean", config, grid_shape=shape, progress=False)
    runs = []
    for seed in range(1, seeds + 1):
        grid_dir = recapture(clean, work / f"{kind}_{seed}", seed)
        start = time.perf_counter()
        result = characterize_grid(read_grid(grid_dir))
        q = quantities(result)
        runs.append({"seed": seed, "seconds": time.perf_counter() - start, "quantities": q})
        shutil.rmtree(grid_dir)
        flags = [name for name, v in q.items() if significant_at(v, Z_SIGNIFICANT)]
        print(f"{kind} seed {seed}: {result.verdict.recommended_model}; significant at Z = "
              f"{Z_SIGNIFICANT:g}: {', '.join(flags) or 'none'}", flush=True)
    return runs


def _wrapped(deviation: float, name: str) -> float:
    return (deviation + 180.0) % 360.0 - 180.0 if name.endswith("rotation_deg") else deviation


def summarise(runs: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    names = sorted({n for r in runs["field_free"] for n in r["quantities"]})
    fpr = {}
    for z in THRESHOLDS:
        per = {n: float(np.mean([significant_at(r["quantities"][n], z)
                                 for r in runs["field_free"]])) for n in names}
        # magnification is a real effect on both cameras (the PSF moves): not a false positive
        pooled = [significant_at(r["quantities"][n], z) for r in runs["field_free"]
                  for n in names if n != "shift_map.magnification"]
        fpr[str(z)] = {"per_quantity": per, "pooled": float(np.mean(pooled)),
                       "trials": len(pooled)}
    detection = {n: float(np.mean([significant_at(r["quantities"][n], Z_SIGNIFICANT)
                                   for r in runs["default"]])) for n in names}
    calibration: dict[str, dict[str, Any]] = {}
    for kind, kind_runs in runs.items():
        for n in names:
            # the deviation from the null (a rotation of 180° may read ±180°)
            values = [None if r["quantities"][n].get("value") is None else
                      _wrapped(r["quantities"][n]["value"] - r["quantities"][n]["null"], n)
                      for r in kind_runs]
            sigmas = [r["quantities"][n].get("sigma") for r in kind_runs]
            ok = [(v, s) for v, s in zip(values, sigmas, strict=True)
                  if v is not None and s is not None]
            if len(ok) >= 3:
                v, s = np.array(ok).T
                calibration.setdefault(kind, {})[n] = {
                    "mean": float(v.mean()), "spread": float(v.std(ddof=1)),
                    "rms_sigma": float(np.sqrt(np.mean(s**2))),
                    "spread_over_sigma": float(v.std(ddof=1) / np.sqrt(np.mean(s**2))),
                    "runs": len(ok)}
    return {"false_positive_rate": fpr, "detection_rate_at_Z": detection,
            "calibration": calibration, "Z": Z_SIGNIFICANT}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=12)
    parser.add_argument("--downsample", type=int, default=8)
    parser.add_argument("--grid", default="5x5")
    parser.add_argument("--out", default="bench_significance.json")
    parser.add_argument("--summarise", metavar="JSON",
                        help="only summarise the runs of an earlier --out file")
    args = parser.parse_args()
    if args.summarise:
        import json

        report(summarise(json.loads(Path(args.summarise).read_text())["runs"]))
        return
    shape = tuple(int(v) for v in args.grid.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        runs = {kind: run(kind, args.seeds, args.downsample, shape, Path(tmp))
                for kind in ("field_free", "default")}
    summary = summarise(runs)
    write_json(args.out, {"runs": runs, "summary": summary, "grid": args.grid,
                          "downsample": args.downsample})
    report(summary)


def report(summary: dict[str, Any]) -> None:
    print("false-positive rate on the field-free camera (pooled over quantities):")
    for z, row in summary["false_positive_rate"].items():
        print(f"  Z = {z}: {row['pooled']:.3f} of {row['trials']} "
              + ", ".join(f"{n} {v:.2f}" for n, v in row["per_quantity"].items() if v))
    print(f"detection rate on the default camera at Z = {Z_SIGNIFICANT:g}: "
          + ", ".join(f"{n} {v:.2f}" for n, v in summary["detection_rate_at_Z"].items()))
    print("calibration (spread of the value over noise draws / RMS reported sigma):")
    for kind, rows in summary["calibration"].items():
        print(f"  {kind}: " + ", ".join(f"{n} {r['spread_over_sigma']:.2f}"
                                         for n, r in rows.items()))


if __name__ == "__main__":
    main()
