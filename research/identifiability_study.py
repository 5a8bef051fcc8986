"""Benchmark: how well do N pairs of size S at photon level P determine ``Kv − Kbase`` and
``Kh − Kbase``? (issue 23, item 4; :mod:`research.identifiability`)

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
  (``research.compare.displacement_map``, on the oracle's caustic mask; px, RMS over the mask),
  the mean correlation of one draw's map with the oracle's, and the noise-free fit's mean
  end-point error against the oracle's map.

A cell's displacement maps are "determined to ≤ 0.1 px" when the displacement spread of both
``Kv`` and ``Kh`` is ≤ 0.1 px (``det.``: noise) — whether they are also *right* is the bias
column (the noise-free fit against the oracle).

    python -m research.identifiability_study                      # the default grid
    python -m research.identifiability_study --sizes 32 --pairs 24 --draws 3   # quick

Cells with N·S² above ``--max-pixels`` (default 96·64²) get the Fisher columns only (one
pass over their scenes; the noise level from the first 24 noise-free measurements), up to
``--fisher-max-pixels`` (default 384·128²): on 2 shared cores the Monte-Carlo of the whole
grid (``--max-pixels 6.3e6``) takes hours, not the 20 minutes of the default. The oracle
uses ``--oracle-scenes`` (384) scenes, fewer (at least 128) where they would exceed
``--oracle-max-pixels`` (384·64²). Prints one Markdown table, measured in this run, and the
settings and wall time.
"""

from __future__ import annotations

import argparse
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
    ap.add_argument("--oracle-max-pixels", type=float, default=384 * 64 * 64,
                    help="fewer oracle scenes (at least 128) where scenes*S*S exceeds this")
    ap.add_argument("--max-pixels", type=float, default=96 * 64 * 64,
                    help="skip cells with N*S*S above this (default: what 2 shared cores "
                         "do in ~20 min; 384 * 128 * 128 for the whole grid)")
    ap.add_argument("--fisher-max-pixels", type=float, default=384 * 128 * 128,
                    help="cells above --max-pixels but not above this get the Fisher columns "
                         "only (no Monte-Carlo)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="also write every number to this JSON file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from ekdun.data.bench_spec import VirtualBenchSpec, dense_model_for, make_scenes
    from psfkit.fitting.pairs.batches import PairBatches
    from psfkit.io.jsonable import write_json
    from research.identifiability import (
        difference_fisher,
        fit_unconstrained,
        monte_carlo,
        noise_variance,
    )
    from research.oracles import operator_oracle

    t_start = time.perf_counter()
    read_noise = VirtualBenchSpec().read_noise_e if args.read_noise is None else args.read_noise
    rows, skipped, records = [], [], []
    for size in args.sizes:
        cells = [n for n in args.pairs if n * size * size <= args.fisher_max_pixels]
        skipped.extend(f"N={n}, S={size}" for n in args.pairs if n not in cells)
        if not cells:
            continue
        mc_cells = [n for n in cells if n * size * size <= args.max_pixels]
        spec = VirtualBenchSpec(sensor_shape=(size, size), n_train=max(cells))
        t0 = time.perf_counter()
        n_oracle = max(128, min(args.oracle_scenes,
                                int(args.oracle_max_pixels // (size * size))))
        oracle = operator_oracle(spec, "source", "paper", n_scenes=n_oracle,
                                 check_convergence=False)
        reference = oracle.model.kernels.astype(np.float64)
        ref_norm = {k: float(np.linalg.norm(reference[j] - reference[0]))
                    for j, k in ((1, "v"), (2, "h"))}
        t_oracle = time.perf_counter() - t0
        dense = dense_model_for(spec)
        scenes = make_scenes(spec, "train")
        n_clean = max(mc_cells) if mc_cells else min(24, len(scenes))
        with torch.no_grad():
            clean = dense(torch.as_tensor(scenes[:n_clean], dtype=torch.float64)).numpy()
        print(f"S={size}: oracle ({n_oracle} scenes, {oracle.record['iterations']} "
              f"it., residual {oracle.record['relative_residual']:.1e}) {t_oracle:.0f} s",
              flush=True)
        for n in cells:
            t1 = time.perf_counter()
            run_mc = n in mc_cells
            x = scenes[:n]
            y0 = clean[:n] if run_mc else clean      # Fisher only: the noise level of these
            fisher = difference_fisher(PairBatches(x, "paper", "source", (size, size)), 1.0)
            clean_fit = fit_unconstrained(x, y0, "paper", "source") if run_mc else None
            for photons in args.photons:
                sigma2 = noise_variance(y0, photons, read_noise)
                crb = {k: float(np.sqrt(fisher["crb_sq"][k] * sigma2)) / ref_norm[k]
                       for k in ("v", "h")}
                record = {"S": size, "N": n, "P": photons, "draws": args.draws if run_mc else 0,
                          "noise_rel": float(np.sqrt(sigma2) / np.mean(y0)),
                          "fisher_eig_min": fisher["eig_min"] / sigma2,
                          "fisher_eig_median": fisher["eig_median"] / sigma2,
                          "fisher_eig_max": fisher["eig_max"] / sigma2,
                          "crb_rel": crb, "metrics": None, "determined_0p1px": None}
                head = (f"| {n} | {size} | {photons:g} | {100 * record['noise_rel']:.1f} % | "
                        f"{record['fisher_eig_min']:.2g} … {record['fisher_eig_max']:.2g} | "
                        f"{crb['v']:.3f} / {crb['h']:.3f} |")
                if run_mc:
                    seed = int(size * 1_000_003 + n * 1009 + photons)
                    mc = monte_carlo(x, y0, reference, photons, read_noise, args.draws,
                                     seed=seed, clean_fit=clean_fit)
                    m = mc.metrics
                    det = all(m[k]["disp_spread_px"] <= 0.1 for k in ("v", "h"))
                    record.update(metrics=m, determined_0p1px=det)

                    def vh(key: str, fmt: str, m=m) -> str:
                        return " / ".join(format(m[k][key], fmt) for k in ("v", "h"))

                    rows.append(
                        f"{head} {vh('kernel_spread', '.3f')} | "
                        f"{vh('ncc', '.3f')} | {vh('bias', '.3f')} | "
                        f"{vh('disp_spread_px', '.3f')} | {vh('disp_corr', '+.2f')} | "
                        f"{vh('disp_bias_px', '.3f')} | {vh('ref_rms_px', '.3f')} | "
                        f"{'yes' if det else 'no'} |")
                else:
                    rows.append(f"{head} (Fisher only) | | | | | | | |")
                record["seconds"] = time.perf_counter() - t1
                records.append(record)
                print(rows[-1], flush=True)
                if args.json:
                    write_json(args.json, records)   # after every row, atomically
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
    print(f"draws {args.draws}, read noise {read_noise} e-, oracle scenes {args.oracle_scenes} "
          f"(at most {args.oracle_max_pixels:g} px in all, at least 128), "
          f"threads {args.threads}; wall {time.perf_counter() - t_start:.0f} s")
    if skipped:
        print("skipped (N*S^2 > --fisher-max-pixels):", ", ".join(skipped))


if __name__ == "__main__":
    main()
