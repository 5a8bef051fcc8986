"""Benchmark: ``psfkit fit-eigen`` on a full-resolution 9×9 RGB grid (target ≤ 20 s, 2 cores).

Each repeat runs the command in a fresh process; the median wall time and the peak resident
memory are printed, with the fit's cross-validated errors.

    python benchmarks/bench_fit_eigen.py                 # simulates the grid first (2 min)
    python benchmarks/bench_fit_eigen.py --grid DIR
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = """
import resource, sys
from psfkit.cli import main
extra = ["--figures", sys.argv[3]] if sys.argv[4] == "1" else []
code = main(["fit-eigen", sys.argv[1], "--out", sys.argv[2], *extra, "--quiet"])
print("PEAK", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20)
sys.exit(code)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--figures", action="store_true", help="also time writing the figures")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        grid = args.grid
        if grid is None:
            from psfkit.bench import simulate_grid

            grid = str(simulate_grid(Path(tmp) / "grid", progress=True))
        times, peaks = [], []
        for i in range(args.repeat):
            out = Path(tmp) / f"k{i}.npz"
            t0 = time.perf_counter()
            res = subprocess.run([sys.executable, "-c", CHILD, grid, str(out),
                                  str(Path(tmp) / f"fig{i}"), "1" if args.figures else "0"],
                                 check=True, capture_output=True, text=True)
            times.append(time.perf_counter() - t0)
            peaks.append(float(res.stdout.split("PEAK")[-1]))
            print(f"run {i + 1}: {times[-1]:.1f} s, peak RSS {peaks[-1]:.2f} GiB", flush=True)
        from psfkit.kernelfile import load_kernels

        summary = load_kernels(Path(tmp) / "k0.npz").provenance["fit"]
    label = "with figures" if args.figures else "kernel file only"
    print(f"fit-eigen 9x9 grid ({label}): median {statistics.median(times):.1f} s over "
          f"{len(times)} runs (target <= 20 s), peak RSS {max(peaks):.2f} GiB")
    print("held-out relative error: " + json.dumps(
        summary["cross_validation"]["held_out_relative_error"]))


if __name__ == "__main__":
    main()
