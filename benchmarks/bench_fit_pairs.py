"""Benchmark: ``psfkit fit-pairs`` on the 7 real DiffuserCam Mirflickr pairs (270×480×3).

Targets (2 cores): shift-invariant fit ≤ 30 s, eigen-kernel fit ≤ 60 s. Each model is fitted
with the default constraints (non-negative kernels: CG, then projected Newton-CG) and without
(``--no-nonneg``: the CG fit alone), each repeat in a fresh process (import and reading
included); medians and ratios are from this one run, with the CPU time of the process (the
fairer figure on a shared machine). ``--leave-one-out`` adds the held-out
relative prediction errors of both models, constrained and not, side by side (the issue's
targets: EK ≤ 0.75 × SI; constrained no worse than unconstrained) at the chosen
``--downsample``.

    python benchmarks/bench_fit_pairs.py
    python benchmarks/bench_fit_pairs.py --repeat 1 --leave-one-out --downsample 2

``--scaling DATA`` (issue 23) instead times ``psfkit fit-pairs DATA/train --basis ek
--convention source`` (defaults otherwise) against pairs × size, on the first N pairs of a
128 × 128 virtual-bench dataset (``ekdun make-dataset DATA --sensor 128 128 --n-train 384
--photons 20000 --no-oracle``), binned 2 × 2 for the 64 × 64 rows: the exact streaming solver
of this tree ("new") and, where ``N·H·W`` is at most ``--old-max`` pixels, the early-stopped CG
of the code at ``--old-ref`` ("old", run from a ``git archive`` of that commit in the same run),
each in a fresh process; wall time, CPU time and peak RSS.

    python benchmarks/bench_fit_pairs.py --scaling /tmp/ds128 --old-max 1572864

Measured (issue 23, 2 shared cores, one run; old = 89f2aa1):

| pairs | size | solver | wall s | CPU s | peak RSS GiB |
|---|---|---|---|---|---|
| 96 | 64 | old | 7.6 | 14.0 | 0.50 |
| 96 | 64 | new | 7.4 | 13.7 | 0.50 |
| 96 | 128 | old | 70.7 | 139.7 | 0.80 |
| 96 | 128 | new | 61.7 | 121.9 | 0.80 |
| 192 | 128 | new | 140.3 | 277.5 | 1.14 |
| 384 | 128 | new | 208.0 | 409.7 | 1.90 |

The new solver runs to a relative residual of 1e-6 (the old one stopped after 60 CG and 100
projected iterations, unconverged) in about the old one's time per pair; the acceptance setting
(384 pairs of 128 × 128 × 3, paper basis) takes 3.5 min and 1.9 GiB (the issue measured
11 min 52 s and 2.6 GB for the old solver, on a busier machine; not re-run here).

Those rows stopped the non-negative step after 100 FISTA iterations (the default then). With
the default since (projected Newton-CG to a KKT residual of 1e-10, its CG on float32 products,
CPU batches kept under glibc's reuse threshold), one run of the acceptance setting on the idle
machine: 5 min 20 s wall, 624 s CPU, 3.0 GB peak RSS, 39 Newton steps (the first Newton
solver, 40 float64 CG iterations per step and 16-pair batches: 58 min on one contended
thread). The other rows were not re-run.

With ``--fit-flags '--nonneg-solver newton' --old-ref c4ffe7c`` (the first Newton solver), one
run on the idle machine; the "old" rows of that run imported this tree's psfkit (the children
ran in the repository, whose directory comes first on ``sys.path``; fixed since, so the rows of
the table above may have the same fault), so the old solver's 96 × 128 row below is a separate
run of ``psfkit fit-pairs --nonneg-solver newton`` from ``git archive c4ffe7c`` on the same 96
pairs, minutes later on the same idle machine:

| pairs | size | solver | wall s | CPU s | peak RSS GiB |
|---|---|---|---|---|---|
| 96 | 64 | new | 13.7 | 26.5 | 0.50 |
| 96 | 128 | old (c4ffe7c, separate run) | 333.3 | 653.9 | 0.84 |
| 96 | 128 | new | 77.0 | 151.9 | 1.01 |
| 192 | 128 | new | 180.4 | 333.6 | 1.57 |
| 384 | 128 | new | 285.5 | 565.3 | 3.02 |

New / old at 96 × 128: 0.23 wall (32 vs 36 Newton steps; the old solver spent 254 s of its CPU
time in the kernel, page-faulting its 43 MB batch temporaries). Both reach the same kernels
(difference NCC 1 − 2e-10).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = """
import resource, sys
from psfkit.cli import main
code = main(["fit-pairs", sys.argv[1], "--basis", sys.argv[2], "--out", sys.argv[3],
             "--downsample", sys.argv[4], "--quiet", *sys.argv[5:]])
usage = resource.getrusage(resource.RUSAGE_SELF)
print("CPU", usage.ru_utime + usage.ru_stime)
print("PEAK", usage.ru_maxrss / 2**20)
sys.exit(code)
"""
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "dlmd_mirflickr"
VARIANTS = {"constrained": [], "unconstrained": ["--no-nonneg"]}


SCALING_CHILD = """
import resource, sys, time
from psfkit.cli import main
t0 = time.perf_counter()
code = main(["fit-pairs", sys.argv[1], "--basis", "ek", "--convention", "source",
             "--out", sys.argv[2], "--quiet", *sys.argv[3:]])
print("WALL", time.perf_counter() - t0)
usage = resource.getrusage(resource.RUSAGE_SELF)
print("CPU", usage.ru_utime + usage.ru_stime)
print("PEAK", usage.ru_maxrss / 2**20)
sys.exit(code)
"""
#: (pairs, sensor side) of the scaling rows; the last is the issue's acceptance setting
SCALING = ((96, 64), (96, 128), (192, 128), (384, 128))


def scaling(data: str, old_ref: str, old_max: int, flags: list[str] | None = None) -> None:
    """Time and peak memory of fit-pairs (with ``flags``) against pairs × size, old vs new,
    in one run."""
    import numpy as np

    from psfkit.cli.pairs_cmd import _load

    full = {}
    repo = Path(__file__).resolve().parents[1]
    print("| pairs | size | solver | wall s | CPU s | peak RSS GiB |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        old_tree = Path(tmp) / "old"
        old_tree.mkdir()
        archive = subprocess.run(["git", "-C", str(repo), "archive", old_ref, "psfkit"],
                                 capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(old_tree)], input=archive, check=True)
        for n, side in SCALING:
            pairs = Path(tmp) / f"pairs{n}_{side}"
            (pairs / "scene").mkdir(parents=True)
            (pairs / "measurement").mkdir()
            if side not in full:
                full.clear()
                full[side] = _load(str(Path(data) / "train"), 128 // side)[1:]
            x, y = full[side]
            for i in range(n):
                np.save(pairs / "scene" / f"p{i:04d}.npy", np.moveaxis(x[i], 0, -1))
                np.save(pairs / "measurement" / f"p{i:04d}.npy", np.moveaxis(y[i], 0, -1))
            for solver in ("old", "new"):
                if solver == "old" and n * side * side > old_max:
                    print(f"| {n} | {side} | old | (not run: > --old-max) | | |", flush=True)
                    continue
                env = dict(os.environ)
                if solver == "old":
                    env["PYTHONPATH"] = str(old_tree) + os.pathsep + env.get("PYTHONPATH", "")
                with tempfile.TemporaryDirectory() as work:
                    # cwd outside the repository: with ``-c`` the working directory comes
                    # first on sys.path, before PYTHONPATH, and would import this tree's
                    # psfkit as the "old" one
                    res = subprocess.run([sys.executable, "-c", SCALING_CHILD, str(pairs),
                                          str(Path(work) / "k.npz"), *(flags or [])],
                                         capture_output=True, text=True, env=env, cwd=work)
                if res.returncode:
                    sys.exit(res.stderr.strip())
                value = {key: float(res.stdout.split(key)[-1].split()[0])
                         for key in ("WALL", "CPU", "PEAK")}
                print(f"| {n} | {side} | {solver} | {value['WALL']:.1f} | {value['CPU']:.1f} "
                      f"| {value['PEAK']:.2f} |", flush=True)
            shutil.rmtree(pairs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=os.environ.get("PSFKIT_DLMD", str(DEFAULT_DATA)))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--leave-one-out", action="store_true")
    parser.add_argument("--scaling", metavar="DATA",
                        help="virtual-bench dataset: time fit-pairs against pairs x size")
    parser.add_argument("--old-ref", default="89f2aa1",
                        help="commit of the old solver for --scaling (default: before issue 23)")
    parser.add_argument("--fit-flags", default="",
                        help="extra fit-pairs flags of both solvers in --scaling (e.g. "
                             "'--nonneg-solver newton' against a ref that had it)")
    parser.add_argument("--old-max", type=int, default=96 * 128 * 128,
                        help="run the old solver only up to this many pixels N*H*W")
    args = parser.parse_args()
    if args.scaling:
        scaling(args.scaling, args.old_ref, args.old_max, args.fit_flags.split())
        return
    medians = {}
    with tempfile.TemporaryDirectory() as tmp:
        for model, target in (("si", 30.0), ("ek", 60.0)):
            for variant, flags in VARIANTS.items():
                times, peaks, cpus = [], [], []
                for i in range(args.repeat):
                    out = Path(tmp) / f"{model}{variant}{i}.npz"
                    t0 = time.perf_counter()
                    res = subprocess.run([sys.executable, "-c", CHILD, args.pairs, model,
                                          str(out), str(args.downsample), *flags],
                                         capture_output=True, text=True)
                    times.append(time.perf_counter() - t0)
                    if res.returncode:
                        sys.exit(res.stderr.strip())
                    peaks.append(float(res.stdout.split("PEAK")[-1]))
                    cpus.append(float(res.stdout.split("CPU")[-1].split()[0]))
                    print(f"{model} {variant} run {i + 1}: {times[-1]:.1f} s ({cpus[-1]:.1f} s "
                          f"CPU), peak RSS {peaks[-1]:.2f} GiB", flush=True)
                medians[model, variant] = statistics.median(times)
                print(f"fit-pairs --basis {model} ({variant}): median "
                      f"{medians[model, variant]:.1f} s over {len(times)} runs (target <= "
                      f"{target:.0f} s; CPU {statistics.median(cpus):.1f} s), peak RSS "
                      f"{max(peaks):.2f} GiB", flush=True)
    for variant in VARIANTS:
        print(f"ratio EK/SI fit time ({variant}): "
              f"{medians['ek', variant] / medians['si', variant]:.2f}")
    if args.leave_one_out:
        held_out(args.pairs, args.downsample)


def held_out(pairs: str, downsample: int) -> None:
    """Leave-one-out errors of SI and EK, constrained (default options) and not."""
    from psfkit.io import read_pairs
    from psfkit.pairs_fit import PairFitOptions, downsample_pairs, leave_one_out

    x, y = downsample_pairs(*read_pairs(pairs).load_all(), downsample)
    errors = {}
    for name, basis in (("si", "si"), ("ek", "paper")):
        for variant in VARIANTS:
            t0 = time.perf_counter()
            options = PairFitOptions(basis=basis, nonneg=variant == "constrained")
            e = errors[name, variant] = leave_one_out(x, y, options, progress=True)
            print(f"leave-one-out {name} {variant} ({x.shape[-2]}x{x.shape[-1]}): held-out "
                  f"relative error mean {e['mean_raw']:.4f} raw, {e['mean_scaled']:.4f} scaled "
                  f"(per pair scaled: {', '.join(f'{v:.3f}' for v in e['scaled'])}); "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    print("| model | constrained raw / scaled | unconstrained raw / scaled |")
    for name in ("si", "ek"):
        c, u = errors[name, "constrained"], errors[name, "unconstrained"]
        print(f"| {name} | {c['mean_raw']:.4f} / {c['mean_scaled']:.4f} | "
              f"{u['mean_raw']:.4f} / {u['mean_scaled']:.4f} |")
    for kind in ("raw", "scaled"):
        for variant in VARIANTS:
            ratio = (errors["ek", variant][f"mean_{kind}"]
                     / errors["si", variant][f"mean_{kind}"])
            print(f"held-out EK/SI ({kind}, {variant}): {ratio:.3f} (target <= 0.75)")


if __name__ == "__main__":
    main()
