"""Benchmark: every eigen-kernel estimator against the oracle (issue 23, item 3).

On a virtual-bench dataset (``ekdun make-dataset``; its oracles under ``DATA/oracle/``, written
by :func:`research.oracles.write_dataset_oracles` where absent, ``--oracle-scenes`` scenes):

- the grid fit, ``psfkit fit-eigen DATA/grid --convention {source,sensor}`` (``--cv-bases
  none``: the cross-validation does not change the kernels);
- the pairs fit, ``psfkit fit-pairs DATA/train --basis ek --convention {source,sensor}``,
  constrained (the default: non-negative, per-pair scale) and unconstrained (``--no-nonneg``);
- optionally learned kernel files (``--learned RUN/kernels_learned.npz ...``, EK-DUN),

each compared (``research.compare.compare_kernels(A, B)``, B the reference) with the operator
oracle of its convention (``oracle/paper_{c}.npz``) and the PSF oracle
(``oracle/psf_paper_{c}.npz``), and the grid fit with the pairs fits. Metrics per correction
kernel ``v`` / ``h``: difference-kernel NCC, displacement-map correlation and mean end-point
error (px), principal angles (°) between the two kernel spans, and the mean relative
prediction error of A on the dataset's test scenes through the dense model, noise-free
(``A_dense x``; raw, and with the best scale per pair).

    python -m research.estimators_vs_oracle /tmp/ds64          # made if absent
    python -m research.estimators_vs_oracle /tmp/ds128 --sensor 128 128 \\
        --n-train 384 --photons 20000
    python -m research.estimators_vs_oracle /tmp/ds64 --learned runs/x/kernels_learned.npz
    python -m research.estimators_vs_oracle /tmp/ds128 --work W --reuse --white-scenes 384

``--white-scenes N`` adds the operator oracle of N white-noise scenes (source side), which a
grid fit estimates (``research/oracle_gap.py``: the PSF oracle and the white-scene
operator oracle are the same least squares up to the field sampling and the crop).
``--nonneg-oracle`` adds the non-negative operator oracle of each convention (the dataset's
oracle scenes, ``operator_oracle(nonneg=True)``), which a non-negative pairs fit estimates.

Prints one Markdown table, measured in this run, and the fit times.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def _fit(args: list[str], reuse: bool = False) -> float | None:
    """Run ``psfkit ARGS``; its wall time, or None when ``reuse`` finds its output."""
    from psfkit.cli import main

    if reuse and Path(args[args.index("--out") + 1]).is_file():
        return None
    t0 = time.perf_counter()
    code = main(args)
    if code:
        raise SystemExit(f"psfkit {' '.join(args)} failed ({code})")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="virtual-bench dataset (made with the options below if absent)")
    ap.add_argument("--sensor", type=int, nargs=2, default=None)
    ap.add_argument("--n-train", type=int, default=None)
    ap.add_argument("--photons", type=float, default=None)
    ap.add_argument("--oracle-scenes", type=int, default=None)
    ap.add_argument("--learned", nargs="*", default=[], help="more kernel files to score")
    ap.add_argument("--work", help="folder for the fitted kernel files (default: temporary)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="also write every number to this JSON file")
    ap.add_argument("--white-scenes", type=int, default=0,
                    help="also compare with the operator oracle of N white-noise scenes "
                         "(source side): the estimand of a grid fit (research/oracle_gap.py)")
    ap.add_argument("--nonneg-oracle", action="store_true",
                    help="also compare with the non-negative operator oracle of each "
                         "convention (the estimand of a non-negative pairs fit)")
    ap.add_argument("--nonneg-iterations", type=int, default=50,
                    help="most projected Newton steps of the non-negative oracle (default 50; "
                         "it stops at a KKT residual of 1e-9)")
    ap.add_argument("--conventions", nargs="+", default=["source", "sensor"],
                    choices=("source", "sensor"))
    ap.add_argument("--no-unconstrained", action="store_true",
                    help="skip the unconstrained pairs fits (--no-nonneg)")
    ap.add_argument("--reuse", action="store_true",
                    help="reuse the kernel files already in --work instead of refitting")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from ekdun.data.bench_spec import VirtualBenchSpec, dense_model_for, make_scenes
    from ekdun.data.virtual_bench import make_virtual_bench, read_manifest
    from psfkit.fitting.pairs.fit import predict, relative_errors
    from psfkit.forward.kernelfile import load_kernels, save_kernels
    from research.compare import compare_kernels
    from research.oracles import operator_oracle, white_scenes, write_dataset_oracles

    data = Path(args.data)
    t0 = time.perf_counter()
    if read_manifest(data) is None:
        overrides = {k: v for k, v in (("sensor_shape", tuple(args.sensor) if args.sensor
                                        else None), ("n_train", args.n_train),
                                       ("photons", args.photons)) if v is not None}
        make_virtual_bench(data, VirtualBenchSpec(**overrides), progress=False)
        print(f"made {data} in {time.perf_counter() - t0:.0f} s", flush=True)
    # the dataset's oracles (kept where it has them, of these scenes)
    _, computed = write_dataset_oracles(data, n_scenes=args.oracle_scenes)
    if computed:
        print(f"wrote {data / 'oracle'} in {time.perf_counter() - t0:.0f} s", flush=True)
    manifest = read_manifest(data)
    assert manifest is not None
    spec = VirtualBenchSpec.from_dict(manifest["spec"])
    oracle_files = manifest["oracle"]["files"]

    work_ctx = tempfile.TemporaryDirectory() if args.work is None else None
    work = Path(args.work or work_ctx.name)   # type: ignore[union-attr]
    work.mkdir(parents=True, exist_ok=True)
    models: dict[str, Path] = {}
    times: dict[str, float | None] = {}
    variants = [("pairs fit", [])] + ([] if args.no_unconstrained
                                      else [("pairs fit, --no-nonneg", ["--no-nonneg"])])
    for c in args.conventions:
        models[f"grid fit ({c})"] = work / f"grid_{c}.npz"
        times[f"grid fit ({c})"] = _fit(["fit-eigen", str(data / "grid"), "--convention", c,
                                         "--cv-bases", "none", "--quiet", "--overwrite",
                                         "--out", str(models[f"grid fit ({c})"])],
                                        args.reuse)
        for label, extra in variants:
            name = f"{label} ({c})"
            models[name] = work / f"pairs_{c}{'_free' if extra else ''}.npz"
            times[name] = _fit(["fit-pairs", str(data / "train"), "--basis", "ek",
                                "--convention", c, "--quiet", "--overwrite", *extra,
                                "--out", str(models[name])], args.reuse)
        print(f"{c}: fitted", flush=True)
    for path in args.learned:
        models[f"learned {path}"] = Path(path)

    test = make_scenes(spec, "test").astype(np.float64)
    with torch.no_grad():
        clean = dense_model_for(spec)(torch.as_tensor(test)).numpy()

    def prediction_error(model) -> str:
        err = relative_errors(predict(model, test, dtype=torch.float64), clean)
        return f"{err['raw'].mean():.4f} / {err['scaled'].mean():.4f}"

    loaded = {name: load_kernels(p) for name, p in models.items()}
    refs = {}
    for c in args.conventions:
        refs[f"operator oracle ({c})"] = load_kernels(data / "oracle" / oracle_files[c]["operator"])
        refs[f"PSF oracle ({c})"] = load_kernels(data / "oracle" / oracle_files[c]["psf"])
    if args.white_scenes and "source" in args.conventions:
        white = work / f"white_oracle_source_{args.white_scenes}.npz"
        if not white.is_file():
            t1 = time.perf_counter()
            save_kernels(white, operator_oracle(
                spec, "source", scenes=white_scenes(spec, args.white_scenes),
                check_convergence=False).model)
            times["white-scene oracle"] = time.perf_counter() - t1
        refs["operator oracle, white scenes (source)"] = load_kernels(white)
    for c in args.conventions if args.nonneg_oracle else ():
        n_oracle = int(oracle_files[c]["operator_record"]["n_scenes"])
        path = work / f"nonneg_oracle_{c}_{n_oracle}.npz"
        if not path.is_file():
            t1 = time.perf_counter()
            result = operator_oracle(spec, c, n_scenes=n_oracle, check_convergence=False,
                                     nonneg=True, projected_iterations=args.nonneg_iterations)
            save_kernels(path, result.model)
            times[f"non-negative oracle ({c})"] = time.perf_counter() - t1
            print(f"non-negative oracle ({c}): {result.record['projected']}", flush=True)
        refs[f"operator oracle, non-negative ({c})"] = load_kernels(path)
    pairs = []
    for name, model in loaded.items():
        for ref_name, ref in refs.items():
            if ref.convention == model.convention:
                pairs.append((name, model, ref_name, ref))
    if args.white_scenes and "source" in args.conventions:
        for name in ("PSF oracle (source)", "operator oracle (source)"):
            pairs.append((name, refs[name], "operator oracle, white scenes (source)",
                          refs["operator oracle, white scenes (source)"]))
    for c in args.conventions:
        pairs.append((f"PSF oracle ({c})", refs[f"PSF oracle ({c})"],
                      f"operator oracle ({c})", refs[f"operator oracle ({c})"]))
        if args.nonneg_oracle:
            name = f"operator oracle, non-negative ({c})"
            pairs.append((name, refs[name], f"operator oracle ({c})",
                          refs[f"operator oracle ({c})"]))
        for label, _ in variants:
            pairs.append((f"grid fit ({c})", loaded[f"grid fit ({c})"], f"{label} ({c})",
                          loaded[f"{label} ({c})"]))

    header = ("| A | B (reference) | diff. NCC Kv / Kh | disp. corr Kv / Kh | EPE px Kv / Kh | "
              "principal angles ° | pred. error of A, noise-free test (raw / scaled) |")
    rows, records = [], []
    pred_cache: dict[str, str] = {}
    for name, model, ref_name, ref in pairs:
        cmp = compare_kernels(model, ref).learned
        m = cmp.metrics
        disp = {k: m[k]["vs_measured_kernels"] for k in ("v", "h")}
        if name not in pred_cache:
            pred_cache[name] = prediction_error(model)
        record = {"a": name, "b": ref_name,
                  "difference_ncc": {k: m[k]["difference_ncc"] for k in ("v", "h")},
                  "disp_corr": {k: disp[k]["corr"] for k in ("v", "h")},
                  "epe_px": {k: disp[k]["epe_px"] for k in ("v", "h")},
                  "angles_deg": [float(a) for a in cmp.angles_eigen_deg],
                  "prediction_error": pred_cache[name]}
        records.append(record)
        rows.append(
            f"| {name} | {ref_name} | "
            f"{record['difference_ncc']['v']:.3f} / {record['difference_ncc']['h']:.3f} | "
            f"{record['disp_corr']['v']:+.2f} / {record['disp_corr']['h']:+.2f} | "
            f"{record['epe_px']['v']:.3f} / {record['epe_px']['h']:.3f} | "
            f"{', '.join(f'{a:.1f}' for a in record['angles_deg'])} | {pred_cache[name]} |")
        print(rows[-1], flush=True)
    for ref_name, ref in refs.items():
        if ref_name.startswith("operator"):
            pred_cache[ref_name] = prediction_error(ref)
    print()
    print(f"dataset {data}: {spec.sensor_shape[0]}x{spec.sensor_shape[1]}, {spec.n_train} "
          f"train / {spec.n_test} test pairs, photons {spec.photons:g}; threads {args.threads}")
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for row in rows:
        print(row)
    print()
    print("prediction error of the operator oracles (raw / scaled): " + "; ".join(
        f"{k}: {v}" for k, v in pred_cache.items() if k.startswith("operator")))
    print("fit times (s): " + ", ".join(f"{k} {v:.0f}" if v is not None else f"{k} reused"
                                        for k, v in times.items()))
    if args.json:
        from psfkit.io.jsonable import write_json

        write_json(args.json, {"records": records, "times": times, "spec": spec.to_dict()})
    if work_ctx is not None:
        work_ctx.cleanup()


if __name__ == "__main__":
    main()
