"""Benchmark: ``psfkit fit-pairs`` on the 7 real DiffuserCam Mirflickr pairs (270×480×3).

Targets (2 cores): shift-invariant fit ≤ 30 s, eigen-kernel fit ≤ 60 s. Each model is fitted
with the default constraints (non-negative kernels: CG, then projected FISTA) and without
(``--no-nonneg``: the CG fit alone), each repeat in a fresh process (import and reading
included); medians and ratios are from this one run, with the CPU time of the process (the
fairer figure on a shared machine). ``--leave-one-out`` adds the held-out
relative prediction errors of both models, constrained and not, side by side (the issue's
targets: EK ≤ 0.75 × SI; constrained no worse than unconstrained) at the chosen
``--downsample``.

    python benchmarks/bench_fit_pairs.py
    python benchmarks/bench_fit_pairs.py --repeat 1 --leave-one-out --downsample 2
"""

from __future__ import annotations

import argparse
import os
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=os.environ.get("PSFKIT_DLMD", str(DEFAULT_DATA)))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--downsample", type=int, default=1)
    parser.add_argument("--leave-one-out", action="store_true")
    args = parser.parse_args()
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
