"""``python -m research.compare``: learned eigen-kernels (a trained EK-DUN's) vs the measured PSF
grid, or any kernel file against another (``python -m research.compare A.npz B.npz``, B as the
measured side). Was ``psfkit compare`` (a study of the paper's Fig. 7, not a product command)."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from psfkit.choices import FLOW_METHODS
from psfkit.cli.main import OneLineArgumentParser, run_cli
from psfkit.cli.options import add_preprocess_options, preprocess_options
from psfkit.forward.kernelfile import load_kernels
from psfkit.io import OutputTransaction
from psfkit.io.flag_ranges import FLAGS, flag

#: ``--smooth`` takes the range of psfkit's other smoothing sigma.
SMOOTH = {"--smooth": FLAGS["--mae-smoothing"]}


def build_parser() -> argparse.ArgumentParser:
    p = OneLineArgumentParser(prog="python -m research.compare", description="""
        Did the network learn the physics? Measures the local sub-pixel displacement of the
        caustic in each learned correction kernel (Kv, Kh) relative to Kbase and compares it
        with the eigen-kernels fitted to the grid, with the warps between the centre and edge
        PSFs, and with the grid's PCA modes; or, given a second kernel file instead of a grid,
        with that file's kernels (no warps or PCA then). Writes figures, compare.json and
        compare.html (Fig. 7).""")
    p.add_argument("learned", help="kernel file of the trained model (.npz)")
    p.add_argument("grid", metavar="MEASURED",
                   help="PSF-grid folder of the same camera, or a kernel file (.npz: a grid "
                        "fit, a pairs fit, an oracle) as the measured side")
    p.add_argument("--out", required=True, help="output folder (created; must not exist or "
                                                "be empty unless --overwrite)")
    p.add_argument("--initial", metavar="KERNELS",
                   help="kernel file before training: its numbers are reported next to the "
                        "learned ones")
    p.add_argument("--method", choices=FLOW_METHODS, default="dis",
                   help="dense-flow method of the displacement maps (default dis)")
    p.add_argument("--smooth", type=flag("--smooth", table=SMOOTH), default=3.0, metavar="PX",
                   help="sigma of the masked Gaussian smoothing of displacement maps (px, "
                        "default 3)")
    p.add_argument("--warp-positions", choices=("axes", "all"), default="axes",
                   help="measured warps from the outermost positions on each kernel's axis "
                        "(default) or from every reliable position, fitted jointly")
    p.add_argument("--no-align", action="store_true",
                   help="do not register the learned Kbase to the measured one first")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    add_preprocess_options(p, "preprocessing of the grid")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run_compare)
    return p


def _fmt(value: float | None) -> str:
    return "  n/a" if value is None or not math.isfinite(value) else f"{value:+.3f}"


def run_compare(args: argparse.Namespace) -> int:
    # imported here, not when the parser is built (scipy, OpenCV, matplotlib)
    from research.compare.report import write_comparison

    out = Path(args.out)
    # refuse every bad input before any work (and before anything is written)
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        folder = outputs.folder(out)
        comparison, learned = _compare(args)
        write_comparison(comparison, folder, overwrite=True)   # into the empty temporary
    _print_comparison(args, comparison, learned, out)
    return 0


def _compare(args: argparse.Namespace) -> tuple[Any, Any]:
    from research.compare import CompareOptions, check_learned, compare_kernels, load_grid

    learned = load_kernels(args.learned)
    check_learned(learned, args.learned)
    initial = load_kernels(args.initial) if args.initial else None
    # a kernel file is compared as it is; a grid folder is validated first
    grid = args.grid if Path(args.grid).suffix == ".npz" else load_grid(args.grid)
    options = CompareOptions(flow_method=args.method, smooth_px=args.smooth,
                             warp_positions=args.warp_positions, align=not args.no_align,
                             preprocess=preprocess_options(args))
    comparison = compare_kernels(learned, grid, initial=initial, options=options,
                                 progress=not args.quiet)
    return comparison, learned


def _print_comparison(args: argparse.Namespace, comparison: Any, learned: Any, out: Path
                      ) -> None:
    what = "kernel file" if Path(args.grid).suffix == ".npz" else "grid"
    print(f"compared {args.learned} ({', '.join(learned.kernel_names)}) with {what} "
          f"{args.grid}; wrote {out}")
    print("  displacement-map correlation (Pearson; n/a = no displacement):")
    for label, row in comparison.headline().items():
        print(f"    {label:8s} " + "  ".join(f"{k} {_fmt(v)}" for k, v in row.items()))
    for name, agreement in comparison.measured_kernels_vs_warp.items():
        print(f"  measured K_{name} vs measured warp: corr {_fmt(agreement['corr'])}")
    for cmp in (comparison.learned, comparison.initial):
        if cmp is not None and cmp.angles_pca_deg is not None:
            print(f"  principal angles {cmp.label} vs top PCA modes (deg): "
                  + ", ".join(f"{a:.1f}" for a in cmp.angles_pca_deg))
    for vs, split in comparison.kernel_change.items():
        if not isinstance(split, dict):
            continue
        print(f"  kernel change {vs.replace('_', ' ')} (gain / light fractions gain, pedestal, "
              "displacement, other):")
        for name, part in split.items():
            if name == "all":
                print(f"    all     outside-support mass {part['outside_mass_fraction']:.3f}, "
                      f"pedestal share of change {part['pedestal_share_of_change']:.3f}")
                continue
            f = part["fractions"]
            print(f"    K_{name:5s} gain {part['gain']:+.3f}  " + "  ".join(
                f"{k} {f[k]:.3f}" for k in ("gain", "pedestal", "displacement", "other")))
    for note in comparison.notes:
        print(f"  note: {note}")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the comparison with ``argv`` (default: the process arguments); returns the exit code."""
    return run_cli("python -m research.compare", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
