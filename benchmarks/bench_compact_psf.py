"""Benchmark: a compact PSF on full frames and on pre-centred cut-outs (issue 43, item 3).

The compact bench (``research.compact_bench.simulate_compact_scan``): a field of ``--positions``
stars (a 3 px Airy PSF, brightness over 10×, Poisson–Gaussian noise) at irregular known
positions on ``--frame``² frames, and the same scan cut into ``--cutout``² cut-outs around each
star (``cutout_scan``: the same pixels, the same noise). Both are characterized and fitted
(``fit-eigen`` with gain compensation); the registration error against the truth, the MAE, the
gain error, the reliability, the working region and binning of the eigen fit, its held-out
cross-validation and the times are printed, one column per frame size, and written to ``--out``
(JSON). A frame-size-independent analysis gives the same numbers in both columns.

    python benchmarks/bench_compact_psf.py --out /tmp/compact.json
    python benchmarks/bench_compact_psf.py --frame 2048 --width-growth 1 --ellipticity 0.5
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.characterization.characterize import (
    RELIABLE_OVERLAP,
    CharacterizeOptions,
    characterize_grid,
)
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.io import read_grid
from psfkit.io.jsonable import write_json

# research/ (not installed) holds the compact bench: import it from this checkout
sys.path.append(str(Path(__file__).resolve().parents[1]))
from research.compact_bench import (
    CompactCamera,
    cutout_scan,
    read_compact_truth,
    simulate_compact_scan,
)


def measure(scan: Path) -> dict[str, Any]:
    """Characterization and eigen fit of one scan, against its truth."""
    truth = read_compact_truth(scan)
    grid = read_grid(scan)
    start = time.perf_counter()
    result = characterize_grid(grid, CharacterizeOptions(steps=("register", "gain", "mae")))
    characterize_s = time.perf_counter() - start
    positions = sorted(result.positions, key=lambda p: p.col)
    index = [p.col for p in positions]
    shift = np.array([p.shift for p in positions])
    error = np.hypot(*(shift - truth.shift_px[index]).T)
    mae = np.array([p.mae_gain_compensated for p in positions])[1:]
    gain = np.array([p.gain for p in positions])
    radius = np.hypot(*truth.field_deg[index][1:].T)
    start = time.perf_counter()
    fit = fit_eigen_grid(grid, EigenFitOptions(gain_compensate=True))
    fit_s = time.perf_counter() - start
    working = fit.summary()["working_region"]
    cv = fit.cv or {}
    return {
        "frame": list(grid.image_shape[1:]),
        "accepted": len(result.positions), "excluded": len(result.excluded),
        "reliable": int(sum(p.support_overlap >= RELIABLE_OVERLAP for p in positions)),
        "sensor_overlap_below_half": int(sum(p.overlap < RELIABLE_OVERLAP for p in positions)),
        "registration_error_rms_px": float(np.sqrt(np.mean(error**2))),
        "registration_error_max_px": float(error.max()),
        "mae_gain_compensated_median": float(np.median(mae)),
        "mae_vs_field_radius_correlation": float(np.corrcoef(radius, mae)[0, 1]),
        "gain_error_max": float(np.max(np.abs(gain / (truth.flux_e[index]
                                                      / truth.flux_e[0]) - 1))),
        "working_region": working,
        "held_out_relative_error": cv.get("held_out_relative_error"),
        "cv_best": cv.get("best"),
        "characterize_s": characterize_s, "fit_eigen_s": fit_s,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--positions", type=int, default=117)
    parser.add_argument("--frame", type=int, default=1024, help="frame side, px")
    parser.add_argument("--cutout", type=int, default=63, help="cut-out side, px")
    parser.add_argument("--width-growth", type=float, default=0.0)
    parser.add_argument("--ellipticity", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="write the numbers here (JSON)")
    args = parser.parse_args(argv)
    camera = CompactCamera(width_growth=args.width_growth, ellipticity=args.ellipticity)
    with tempfile.TemporaryDirectory() as tmp:
        full = simulate_compact_scan(Path(tmp) / "full", args.positions,
                                     (args.frame, args.frame), camera, seed=args.seed,
                                     progress=True)
        cut = cutout_scan(full, Path(tmp) / "cut", args.cutout)
        rows = {"full frames": measure(full), "cut-outs": measure(cut)}
    for key in rows["full frames"]:
        print(f"{key:34s}" + "".join(f" {row[key]!s:>24.24s}" for row in rows.values()))
    if args.out:
        write_json(args.out, {"positions": args.positions, "camera": camera.to_dict(),
                              "results": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
