"""Benchmark: simulate a 9×9 RGB PSF grid with the virtual bench, torch vs NumPy optics.

Targets: full resolution (81 × 1080×1440×3, 16-bit) in under 3 minutes on 2 cores with peak
memory under 4 GiB (issue 2), and the torch backend at most 0.5× the NumPy reference path's
time on the same machine in the same run (issue 15). Each run is a fresh process (so its peak
resident memory is its own); the backends alternate, ``--repeat`` runs each, and the medians
and their ratio are printed, with the relative L2 difference of the clean PSFs of the last two
runs (torch vs NumPy).

    python benchmarks/bench_simulate_grid.py                 # full resolution, 3 runs each
    python benchmarks/bench_simulate_grid.py --downsample 4  # the test-sized grid
    python benchmarks/bench_simulate_grid.py --backends torch
    python benchmarks/bench_simulate_grid.py --backends old,torch --old-ref f660dda

``old`` is the code at git ``--old-ref`` (default: f660dda, the start of issue 15), exported
with ``git archive`` and run with its own default backend: the "today's time" of issue 15,
measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = """
import json, resource, sys, time
from psfkit.simulate import BenchConfig, simulate_grid
out, ds, backend = sys.argv[1], int(sys.argv[2]), sys.argv[3]
t0 = time.perf_counter()
extra = {} if backend == "old" else {"backend": backend}   # old code: no backend argument
simulate_grid(out, BenchConfig(downsample=ds), grid_shape=(9, 9), progress=False, **extra)
wall = time.perf_counter() - t0
peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
cpu = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall_s": wall, "peak_rss_gib": peak_kib / 2**20,
                  "cpu_s": cpu.ru_utime + cpu.ru_stime}))
"""


def clean_difference(a: Path, b: Path) -> float:
    """Relative L2 difference of two grids' noise-free PSFs (position by position)."""
    import numpy as np

    x = np.load(a / "ground_truth" / "psfs_clean.npy", mmap_mode="r")
    y = np.load(b / "ground_truth" / "psfs_clean.npy", mmap_mode="r")
    num = den = 0.0
    for i in range(x.shape[0]):
        xi, yi = np.asarray(x[i], np.float64), np.asarray(y[i], np.float64)
        num += float(np.sum((xi - yi) ** 2))
        den += float(np.sum(xi**2))
    return (num / den) ** 0.5


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--backends", default="numpy,torch",
                        help="comma-separated, alternated in this order (default numpy,torch); "
                             "'old': the code at --old-ref")
    parser.add_argument("--old-ref", default="f660dda")
    args = parser.parse_args()
    backends = args.backends.split(",")
    env = dict(os.environ)
    runs: dict[str, list[dict]] = {b: [] for b in backends}
    with tempfile.TemporaryDirectory() as tmp:
        codes = {b: None for b in backends}
        if "old" in backends:
            from bench_fit_eigen import export_code  # same folder as this script

            codes["old"] = export_code(args.old_ref, Path(tmp) / "old")
        last: dict[str, Path] = {}
        for i in range(args.repeat):
            for backend in backends:
                out = Path(tmp) / f"grid_{backend}_{i}"
                code = codes[backend]
                # the old code's own folder first on sys.path (``python -c`` puts the working
                # directory there)
                res = subprocess.run([sys.executable, "-c", CHILD, str(out),
                                      str(args.downsample), backend],
                                     check=True, capture_output=True, text=True,
                                     cwd=code, env={**env, "PYTHONPATH": str(code)}
                                     if code else env)
                run = json.loads(res.stdout.strip().splitlines()[-1])
                run["disk_mib"] = sum(f.stat().st_size for f in out.rglob("*")
                                      if f.is_file()) / 2**20
                runs[backend].append(run)
                print(f"run {i + 1} {backend:5s}: {run['wall_s']:.1f} s wall, "
                      f"{run['cpu_s']:.1f} s CPU, peak RSS {run['peak_rss_gib']:.2f} GiB, "
                      f"{run['disk_mib']:.0f} MiB written", flush=True)
                if backend in last:
                    import shutil

                    shutil.rmtree(last[backend])
                last[backend] = out
        if {"numpy", "torch"} <= set(last):
            diff = clean_difference(last["numpy"], last["torch"])
            print(f"clean PSFs torch vs numpy: relative L2 difference {diff:.2e} (target < 1e-4)")
    medians = {}
    for backend, rs in runs.items():
        medians[backend] = statistics.median(r["wall_s"] for r in rs)
        cpu = statistics.median(r["cpu_s"] for r in rs)
        peak = max(r["peak_rss_gib"] for r in rs)
        print(f"simulate 9x9 RGB grid, downsample {args.downsample}, {backend}: median "
              f"{medians[backend]:.1f} s wall, {cpu:.1f} s CPU over {len(rs)} run(s) "
              f"(target < 180 s at full resolution), peak RSS {peak:.2f} GiB (target < 4 GiB)")
    for reference in ("numpy", "old"):
        if {reference, "torch"} <= set(medians):
            print(f"ratio torch / {reference} (median wall): "
                  f"{medians['torch'] / medians[reference]:.3f} (target <= 0.5)")


if __name__ == "__main__":
    main()
