"""Benchmark: simulate a 9×9 RGB PSF grid with the virtual bench.

Target (issue 2): full resolution (81 × 1080×1440×3, 16-bit) in under 3 minutes on 2 cores
with peak memory under 4 GiB. Each run is a fresh process so that its peak resident memory
is measured on its own; the median wall time over ``--repeat`` runs is reported.

    python benchmarks/bench_simulate_grid.py                 # full resolution
    python benchmarks/bench_simulate_grid.py --downsample 4  # the test-sized grid
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = """
import json, resource, sys, time
from psfkit.bench import BenchConfig, simulate_grid
out, ds = sys.argv[1], int(sys.argv[2])
t0 = time.perf_counter()
simulate_grid(out, BenchConfig(downsample=ds), grid_shape=(9, 9), progress=False)
wall = time.perf_counter() - t0
peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"wall_s": wall, "peak_rss_gib": peak_kib / 2**20}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    runs = []
    for i in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "grid"
            res = subprocess.run([sys.executable, "-c", CHILD, str(out), str(args.downsample)],
                                 check=True, capture_output=True, text=True)
            run = json.loads(res.stdout.strip().splitlines()[-1])
            run["disk_mib"] = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**20
            runs.append(run)
            print(f"run {i + 1}: {run['wall_s']:.1f} s, peak RSS {run['peak_rss_gib']:.2f} GiB, "
                  f"{run['disk_mib']:.0f} MiB written", flush=True)
    wall = statistics.median(r["wall_s"] for r in runs)
    peak = max(r["peak_rss_gib"] for r in runs)
    print(f"simulate 9x9 RGB grid, downsample {args.downsample}: median {wall:.1f} s over "
          f"{len(runs)} run(s) (target < 180 s at full resolution), peak RSS {peak:.2f} GiB "
          "(target < 4 GiB)")


if __name__ == "__main__":
    main()
