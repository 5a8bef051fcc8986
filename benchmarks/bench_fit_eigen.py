"""Benchmark: ``psfkit fit-eigen`` on a full-resolution 9×9 RGB grid, this code vs an older one.

Targets (issues 2 and 15): ≤ 20 s on 2 cores, and ≤ 0.5× the time of the code at ``--old-ref``
(default ``main``) on the same machine in the same run. The old code is exported from git
(``git archive``) into a temporary folder; each repeat runs the command in a fresh process for
the old and the new code, alternating, and the medians of the wall times, their ratio, the peak
resident memory and the largest kernel difference between the two (relative to the largest
kernel value) are printed, with the fit's cross-validated errors.

    python benchmarks/bench_fit_eigen.py                 # simulates the grid first (2 min)
    python benchmarks/bench_fit_eigen.py --grid DIR --repeat 3 --old-ref main
    python benchmarks/bench_fit_eigen.py --grid DIR --old-ref none   # new code only
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHILD = """
import resource, sys
from psfkit.cli import main
extra = ["--figures", sys.argv[3]] if sys.argv[4] == "1" else []
code = main(["fit-eigen", sys.argv[1], "--out", sys.argv[2], *extra, "--quiet"])
usage = resource.getrusage(resource.RUSAGE_SELF)
print("CPU", usage.ru_utime + usage.ru_stime)
print("PEAK", usage.ru_maxrss / 2**20)
sys.exit(code)
"""


def export_code(ref: str, dest: Path) -> Path:
    """The ``psfkit`` and ``ekdun`` packages as of git ``ref``, extracted under ``dest``
    (both: before issue 11, psfkit imported ekdun, which must then be the same age)."""
    archive = subprocess.run(["git", "archive", "--format=tar", ref, "psfkit", "ekdun"],
                             cwd=ROOT, check=True, capture_output=True).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(dest, filter="data")
    return dest


def kernel_difference(a: Path, b: Path, margin: int = 16) -> tuple[float, float, float]:
    """How two kernel files differ: ``max |Ka − Kb| / max |Ka|`` over all pixels; the same
    over the pixels at least ``margin`` px from the edges once one common scale ``s`` is taken
    out (``Kb·s``, least squares); and ``s``.

    Pixels at the edges are seen by one or two PSFs of the grid only, so their values are set
    by the ridge of a near-singular system and move with the rounding of the sums (the code
    before issue 15's third pass summed its Gram matrices in float32, which made some of them
    indefinite there). Kernel files are normalised by the base kernel's sum, edges included,
    so the edges also move the scale of every pixel.
    """
    import numpy as np

    from psfkit.forward.kernelfile import load_kernels

    ka, kb = load_kernels(a).kernels, load_kernels(b).kernels
    inner = (..., slice(margin, -margin), slice(margin, -margin))
    ia, ib = ka[inner].astype(np.float64), kb[inner].astype(np.float64)
    scale = float(np.sum(ia * ib) / np.sum(ib * ib))
    return (float(np.abs(ka - kb).max() / np.abs(ka).max()),
            float(np.abs(ia - scale * ib).max() / np.abs(ia).max()), scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--old-ref", default="main",
                        help="git revision of the old code ('none': time the new code only)")
    parser.add_argument("--figures", action="store_true", help="also time writing the figures")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        grid = args.grid
        if grid is None:
            from psfkit.simulate import simulate_grid

            grid = str(simulate_grid(Path(tmp) / "grid", progress=True))
        codes = {"new": ROOT}
        if args.old_ref != "none":
            codes["old"] = export_code(args.old_ref, Path(tmp) / "old")
        print("codes: " + ", ".join(f"{name} {code}" for name, code in codes.items()),
              flush=True)
        times: dict[str, list[float]] = {name: [] for name in codes}
        peaks: dict[str, list[float]] = {name: [] for name in codes}
        cpus: dict[str, list[float]] = {name: [] for name in codes}
        for i in range(args.repeat):
            for name, code in codes.items():
                out = Path(tmp) / f"{name}{i}.npz"
                env = {**os.environ, "PYTHONPATH": str(code)}
                t0 = time.perf_counter()
                # run in the code's own folder: ``python -c`` puts the working directory
                # first on sys.path, ahead of PYTHONPATH (from the repository root both
                # runs would import the new code)
                res = subprocess.run([sys.executable, "-c", CHILD, str(Path(grid).resolve()),
                                      str(out), str(Path(tmp) / f"fig{name}{i}"),
                                      "1" if args.figures else "0"],
                                     check=True, capture_output=True, text=True, env=env,
                                     cwd=code)
                times[name].append(time.perf_counter() - t0)
                peaks[name].append(float(res.stdout.split("PEAK")[-1]))
                cpus[name].append(float(res.stdout.split("CPU")[-1].split()[0]))
                print(f"run {i + 1} {name}: {times[name][-1]:.1f} s, CPU {cpus[name][-1]:.1f} s, "
                      f"peak RSS {peaks[name][-1]:.2f} GiB", flush=True)
        from psfkit.forward.kernelfile import load_kernels

        summary = load_kernels(Path(tmp) / "new0.npz").provenance["fit"]
        diff = kernel_difference(Path(tmp) / "old0.npz", Path(tmp) / "new0.npz") \
            if "old" in codes else None
    label = "with figures" if args.figures else "kernel file only"
    medians = {name: statistics.median(t) for name, t in times.items()}
    cpu = {name: statistics.median(t) for name, t in cpus.items()}
    for name in codes:
        print(f"fit-eigen 9x9 grid ({label}), {name} code: median {medians[name]:.1f} s over "
              f"{len(times[name])} runs (target <= 20 s), CPU (user + system) {cpu[name]:.1f} s, "
              f"peak RSS {max(peaks[name]):.2f} GiB")
    if diff is not None:
        # CPU time is the steadier figure on a shared machine (wall time counts other loads)
        print(f"ratio new / old (median wall): {medians['new'] / medians['old']:.3f}, "
              f"(median CPU): {cpu['new'] / cpu['old']:.3f} (target <= 0.5); "
              f"kernels max |new - old| / max |old| = {diff[0]:.1e} everywhere; "
              f"{diff[1]:.1e} at least 16 px from the edges after one common scale "
              f"(old / new = {diff[2]:.6f})")
    print("held-out relative error: " + json.dumps(
        summary["cross_validation"]["held_out_relative_error"]))


if __name__ == "__main__":
    main()
