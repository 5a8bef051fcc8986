"""Benchmark: why the PSF oracle and the operator oracle differ (issue 23).

The grid fit estimates the PSF oracle (the eigen-kernel fit of the noise-free node PSFs) and
a pairs fit the operator oracle (the eigen-kernel model closest to the dense operator over the
dataset's scenes); the two are not the same model
(research/notes/compare-studies.md). This splits their
distance into its causes, one change at a time (``research.oracles``, source convention,
paper basis):

1. **PSF oracle** — the fit of the 9 × 9 node PSFs (:func:`psf_oracle`);
2. **dense PSF oracle** — the fit of the dense model's interpolated PSF at every scene
   pixel (:func:`dense_psf_oracle`): every field point weighted alike, not only the nodes;
3. **dense PSF oracle, cropped** — each PSF counted only where it lands on the sensor;
4. **operator oracle, white scenes** — the operator oracle for scenes of independent
   zero-mean pixels (:func:`white_scenes`, a flat spectrum), by the pairs solver;
5. **operator oracle** — the operator oracle itself, over the dataset's natural and
   dead-leaves scenes, whose spectrum falls with frequency.

3 and 4 are the same least squares in expectation (see :func:`dense_psf_oracle`), solved by
two independent methods: their agreement checks both. So 1 → 2 measures the sampling of the
field, 2 → 3 the crop, 3 → 4 the Monte-Carlo error of the finite scenes, and 4 → 5 the scene
statistics. Each pair is compared as ``bench_estimators_vs_oracle`` does: difference NCC,
displacement-map correlation, end-point error, principal angles, and the noise-free
prediction error on the test scenes (raw / best scale per pair).

    python -m research.oracle_gap                        # 64 × 64 (~3 min, 2 cores)
    python -m research.oracle_gap --sensor 128 128 --scenes 384

Prints one Markdown table, measured in this run.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensor", type=int, nargs=2, default=(64, 64))
    ap.add_argument("--scenes", type=int, default=384,
                    help="scenes of both operator oracles (white and the dataset's)")
    ap.add_argument("--half-fov", type=float, default=30.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="also write every number to this JSON file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from ekdun.data.bench_spec import VirtualBenchSpec, dense_model_for, make_scenes
    from psfkit.fitting.pairs.fit import predict, relative_errors
    from research.compare import compare_kernels
    from research.oracles import (
        dense_psf_oracle,
        operator_oracle,
        psf_oracle,
        white_scenes,
    )

    spec = VirtualBenchSpec(sensor_shape=tuple(args.sensor), half_fov_deg=args.half_fov)
    times: dict[str, float] = {}

    def timed(name, fn, *a, **k):
        t0 = time.perf_counter()
        out = fn(*a, **k)
        times[name] = time.perf_counter() - t0
        print(f"{name}: {times[name]:.0f} s", flush=True)
        return out.model

    models = {
        "PSF oracle": timed("PSF oracle", psf_oracle, spec, "source"),
        "dense PSF oracle": timed("dense PSF oracle", dense_psf_oracle, spec, "source"),
        "dense PSF oracle, cropped": timed("dense PSF oracle, cropped", dense_psf_oracle, spec,
                                           "source", crop=True),
        "operator oracle, white scenes": timed(
            "operator oracle, white scenes", operator_oracle, spec, "source",
            scenes=white_scenes(spec, args.scenes), check_convergence=False),
        "operator oracle": timed("operator oracle", operator_oracle, spec, "source",
                                 n_scenes=args.scenes, check_convergence=False),
    }
    names = list(models)
    test = make_scenes(spec, "test").astype(np.float64)
    with torch.no_grad():
        clean = dense_model_for(spec)(torch.as_tensor(test)).numpy()
    pred = {}
    for name, model in models.items():
        err = relative_errors(predict(model, test, dtype=torch.float64), clean)
        pred[name] = (float(err["raw"].mean()), float(err["scaled"].mean()))

    pairs = [(names[i], names[i + 1]) for i in range(len(names) - 1)]
    pairs += [(a, names[-1]) for a in names[:-2]]
    records = []
    header = ("| A | B (reference) | diff. NCC Kv / Kh | disp. corr Kv / Kh | EPE px Kv / Kh | "
              "principal angles ° |")
    rows = []
    for a, b in pairs:
        cmp = compare_kernels(models[a], models[b]).learned
        m = cmp.metrics
        disp = {k: m[k]["vs_measured_kernels"] for k in ("v", "h")}
        rec = {"a": a, "b": b,
               "difference_ncc": {k: m[k]["difference_ncc"] for k in ("v", "h")},
               "disp_corr": {k: disp[k]["corr"] for k in ("v", "h")},
               "epe_px": {k: disp[k]["epe_px"] for k in ("v", "h")},
               "angles_deg": [float(x) for x in cmp.angles_eigen_deg]}
        records.append(rec)
        rows.append(f"| {a} | {b} | {rec['difference_ncc']['v']:.3f} / "
                    f"{rec['difference_ncc']['h']:.3f} | {rec['disp_corr']['v']:+.2f} / "
                    f"{rec['disp_corr']['h']:+.2f} | {rec['epe_px']['v']:.3f} / "
                    f"{rec['epe_px']['h']:.3f} | "
                    f"{', '.join(f'{x:.1f}' for x in rec['angles_deg'])} |")
    print()
    print(f"bench {spec.sensor_shape[0]}x{spec.sensor_shape[1]}, half FOV {spec.half_fov_deg}°, "
          f"{args.scenes} oracle scenes, source convention, paper basis; threads "
          f"{args.threads}")
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    print("\n".join(rows))
    print()
    print("noise-free prediction error on the test scenes (raw / scaled): " + "; ".join(
        f"{k} {v[0]:.4f} / {v[1]:.4f}" for k, v in pred.items()))
    print("times (s): " + ", ".join(f"{k} {v:.0f}" for k, v in times.items()))
    if args.json:
        from psfkit.io.jsonable import write_json

        write_json(args.json, {"records": records, "prediction_error": pred, "times": times,
                               "spec": spec.to_dict(), "scenes": args.scenes})


if __name__ == "__main__":
    main()
