"""Benchmark: how well do N pairs of size S at photon level P determine ``Kv − Kbase`` and
``Kh − Kbase``? (issue 23, item 4; :mod:`psfkit.identifiability`)

For each sensor size S the virtual bench of ``ekdun make-dataset --sensor S S`` (defaults
otherwise: 9 × 9 grid over ±30°, source-side dense model, read noise 2 e⁻) gives the dense
operator, the training scenes (the first N of the training stream, i.e. the scenes of a dataset
with ``--n-train N``) and the operator oracle (paper basis, source convention, its own scenes:
the truth the spreads are measured against). Per (N, S, P):

- **Fisher**: the eigenvalues of the Fisher information of the difference kernels (Schur
  complement, ``Kbase`` a nuisance) over frequencies and channels, in the no-crop,
  whole-grid, white-noise approximation (per-frequency Gram blocks), and the Cramér–Rao
  relative std of ``Kv − Kbase`` it predicts (``crb``);
- **Monte-Carlo**: ``--draws`` noise realisations of the noise-free measurements ``A_dense x``
  at photon level P (Poisson–Gaussian, the bench's model), each fitted by the exact
  unconstrained least squares (``psfkit fit-pairs --basis ek --convention source --no-scale
  --no-nonneg``, difference prior and ridge 0, to a relative residual of 1e-6): the std over
  draws of the difference kernels relative to the oracle's (``spread``), their mean NCC with
  the oracle's, the noise-free fit's own distance from the oracle (``bias``: model mismatch
  and the finite scenes, no noise), and the std over draws of the displacement maps
  (``psfkit.compare.displacement_map``, on the oracle's caustic mask; px, RMS over the mask),
  the mean correlation of one draw's map with the oracle's, and the noise-free fit's mean
  end-point error against the oracle's map.

A cell's displacement maps are "determined to ≤ 0.1 px" when the displacement spread of both
``Kv`` and ``Kh`` is ≤ 0.1 px (``det.``: noise) — whether they are also *right* is the bias
column (the noise-free fit against the oracle).

    python benchmarks/bench_identifiability.py                      # the default grid
    python benchmarks/bench_identifiability.py --sizes 32 --pairs 24 --draws 3   # quick

Cells with N·S² above ``--max-pixels`` are skipped (and listed). Prints one Markdown table,
measured in this run, and the settings and wall time.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--pairs", type=int, nargs="+", default=[24, 96, 384])
    ap.add_argument("--photons", type=float, nargs="+", default=[2000.0, 20000.0])
    ap.add_argument("--draws", type=int, default=6)
    ap.add_argument("--read-noise", type=float, default=None,
                    help="read noise in electrons (default: the bench's)")
    ap.add_argument("--oracle-scenes", type=int, default=384,
                    help="scenes of the operator oracle per size (default 384, what "
                         "make-dataset uses for 96 training pairs)")
    ap.add_argument("--max-pixels", type=float, default=384 * 128 * 128,
                    help="skip cells with N*S*S above this")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="also write every number to this JSON file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from ekdun.data.bench_spec import VirtualBenchSpec, dense_model_for, make_scenes
    from ekdun.data.oracle import operator_oracle
    from psfkit.identifiability import (
        difference_fisher,
        fit_unconstrained,
        monte_carlo,
        noise_variance,
    )
    from psfkit.pairs_solver import PairBatches

    t_start = time.perf_counter()
    read_noise = VirtualBenchSpec().read_noise_e if args.read_noise is None else args.read_noise
    rows, skipped, records = [], [], []
    for size in args.sizes:
        n_max = max(n for n in args.pairs if n * size * size <= args.max_pixels) \
            if any(n * size * size <= args.max_pixels for n in args.pairs) else 0
        if n_max == 0:
            skipped.extend(f"N={n}, S={size}" for n in args.pairs)
            continue
        spec = VirtualBenchSpec(sensor_shape=(size, size), n_train=n_max)
        t0 = time.perf_counter()
        oracle = operator_oracle(spec, "source", "paper", n_scenes=args.oracle_scenes,
                                 check_convergence=False)
        reference = oracle.model.kernels.astype(np.float64)
        t_oracle = time.perf_counter() - t0
        dense = dense_model_for(spec)
        scenes = make_scenes(spec, "train")
        with torch.no_grad():
            clean = dense(torch.as_tensor(scenes, dtype=torch.float64)).numpy()
        print(f"S={size}: oracle ({args.oracle_scenes} scenes, {oracle.record['iterations']} "
              f"it., residual {oracle.record['relative_residual']:.1e}) {t_oracle:.0f} s",
              flush=True)
        for n in args.pairs:
            if n * size * size > args.max_pixels:
                skipped.append(f"N={n}, S={size}")
                continue
            t1 = time.perf_counter()
            x, y0 = scenes[:n], clean[:n]
            fisher = difference_fisher(PairBatches(x, "paper", "source", (size, size)), 1.0)
            clean_fit = fit_unconstrained(x, y0, "paper", "source")
            for photons in args.photons:
                sigma2 = noise_variance(y0, photons, read_noise)
                seed = int(size * 1_000_003 + n * 1009 + photons)
                mc = monte_carlo(x, y0, reference, photons, read_noise, args.draws,
                                 seed=seed, clean_fit=clean_fit)
                m = mc.metrics
                ref_norm = {k: float(np.linalg.norm(reference[j] - reference[0]))
                            for j, k in ((1, "v"), (2, "h"))}
                crb = {k: float(np.sqrt(fisher["crb_sq"][k] * sigma2)) / ref_norm[k]
                       for k in ("v", "h")}
                det = all(m[k]["disp_spread_px"] <= 0.1 for k in ("v", "h"))
                record = {"S": size, "N": n, "P": photons, "draws": args.draws,
                          "noise_rel": float(np.sqrt(sigma2) / np.mean(y0)),
                          "fisher_eig_min": fisher["eig_min"] / sigma2,
                          "fisher_eig_median": fisher["eig_median"] / sigma2,
                          "fisher_eig_max": fisher["eig_max"] / sigma2,
                          "crb_rel": crb, "metrics": m, "determined_0p1px": det,
                          "seconds": time.perf_counter() - t1}
                records.append(record)

                def vh(key: str, fmt: str, m=m) -> str:
                    return " / ".join(format(m[k][key], fmt) for k in ("v", "h"))

                rows.append(
                    f"| {n} | {size} | {photons:g} | {100 * record['noise_rel']:.1f} % | "
                    f"{record['fisher_eig_min']:.2g} … {record['fisher_eig_max']:.2g} | "
                    f"{crb['v']:.3f} / {crb['h']:.3f} | {vh('kernel_spread', '.3f')} | "
                    f"{vh('ncc', '.3f')} | {vh('bias', '.3f')} | "
                    f"{vh('disp_spread_px', '.3f')} | {vh('disp_corr', '+.2f')} | "
                    f"{vh('disp_bias_px', '.3f')} | {vh('ref_rms_px', '.3f')} | "
                    f"{'yes' if det else 'no'} |")
                print(rows[-1], flush=True)
    header = ("| N | S | P | noise | Fisher eig. (diff.) min … max | CRB rel. std Kv / Kh | "
              "MC spread Kv / Kh | NCC to oracle | bias (noise-free fit) | "
              "disp. spread px | disp. corr to oracle | disp. bias px | oracle disp. RMS px "
              "| ≤ 0.1 px |")
    print()
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for row in rows:
        print(row)
    print()
    print(f"draws {args.draws}, read noise {read_noise} e-, oracle scenes {args.oracle_scenes}, "
          f"threads {args.threads}; wall {time.perf_counter() - t_start:.0f} s")
    if skipped:
        print("skipped (N*S^2 > --max-pixels):", ", ".join(skipped))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(records, fh, indent=1)


if __name__ == "__main__":
    main()
