"""Benchmark: register + MAE + warp of a full-resolution 9×9 RGB PSF grid.

Target (issue 3): 81 × 1080×1440×3 16-bit PSFs in ≤ 60 s on 2 cores, peak memory ≤ 3 GiB.
Each repeat runs in a fresh process (its own peak resident memory); medians are reported,
with the accuracy against the virtual bench's ground truth.

    python benchmarks/bench_characterize_grid.py                 # simulates the grid first
    python benchmarks/bench_characterize_grid.py --grid DIR      # an existing simulated grid
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
import numpy as np
from psfkit.simulate import read_ground_truth
from psfkit.characterization.characterize import RELIABLE_OVERLAP, characterize_grid
from psfkit.io import read_grid
grid = read_grid(sys.argv[1], check_pixels=False)
t0 = time.perf_counter()
result = characterize_grid(grid)
wall = time.perf_counter() - t0
truth = read_ground_truth(sys.argv[1])
err = np.hypot(*np.moveaxis(result.table("shift") - truth.shift_px, -1, 0))
ov = result.table("overlap")
classes = {}
for lo, hi in [(0.7, 1.01), (0.5, 0.7), (0.3, 0.5), (0.0, 0.3)]:
    sel = (ov >= lo) & (ov < hi)
    if sel.any():
        classes[f"{lo:.1f}-{min(hi, 1):.1f}"] = [int(sel.sum()),
                                                float(np.sqrt(np.mean(err[sel] ** 2))),
                                                float(err[sel].max())]
print(json.dumps({
    "wall_s": wall, "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
    "shift_rms_all": float(np.sqrt(np.mean(err ** 2))),
    "shift_by_overlap": classes,
    "gain_err_max": float(np.max(np.abs(result.table("gain") / truth.gain - 1))),
    "growth": result.warp_growth.to_dict() if result.warp_growth else None,
    "anisotropy": result.warp_anisotropy}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", help="simulated grid folder (default: simulate one)")
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        grid = args.grid
        if grid is None:
            from psfkit.simulate import BenchConfig, simulate_grid

            grid = str(simulate_grid(Path(tmp) / "grid", BenchConfig(downsample=args.downsample),
                                     progress=True))
        runs = []
        for i in range(args.repeat):
            res = subprocess.run([sys.executable, "-c", CHILD, grid], check=True,
                                 capture_output=True, text=True)
            runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(f"run {i + 1}: {runs[-1]['wall_s']:.1f} s, peak RSS "
                  f"{runs[-1]['peak_rss_gib']:.2f} GiB", flush=True)
    last = runs[-1]
    print(f"register + gain + MAE + warp, 9x9 grid, downsample {args.downsample}: median "
          f"{statistics.median(r['wall_s'] for r in runs):.1f} s over {len(runs)} runs (target "
          f"<= 60 s at full resolution), peak RSS {max(r['peak_rss_gib'] for r in runs):.2f} GiB "
          "(target <= 3 GiB)")
    print(f"shift error vs ground truth: {last['shift_rms_all']:.3f} px rms overall; by overlap "
          "with the centre PSF [n, rms, max]: " + json.dumps(last["shift_by_overlap"]))
    print(f"gain error max {100 * last['gain_err_max']:.2f}%")
    if last["growth"]:
        print(f"warp residual grows as theta^{last['growth']['exponent']:.2f} "
              f"(+/- {last['growth']['exponent_std']:.2f})")
    if last["anisotropy"]:
        a = last["anisotropy"]
        print(f"tangential/sagittal: measured {a['median_measured']:.2f}, geometric "
              f"{a['median_geometric']:.2f} ({a['positions']} positions)")


if __name__ == "__main__":
    main()
