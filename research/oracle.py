"""An eigen-kernel oracle of an existing virtual-bench dataset, as a kernel file (a thin layer
over :mod:`ekdun.data.oracle`); ``ekdun oracle`` until issue 44, a research instrument now.

    python -m research.oracle DATASET --out oracle.npz [--kind operator|psf] [--no-nonneg]

``make-dataset`` writes the unconstrained operator and PSF oracles of both conventions; this
command computes any of them again with other settings, and the *non-negative* operator
oracle, the estimand of ``psfkit fit-pairs``' default (non-negative) fit, which a dataset does
not carry (minutes at 128², the cost of a fit-pairs).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ekdun.errors import ConfigurationError, InvalidInputError
from psfkit.cli import run_cli
from psfkit.cli.main import add_debug_option
from psfkit.cli.vocabulary import BASIS_ALIASES
from psfkit.validation import OneLineArgumentParser, flag


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m research.oracle``."""
    p = OneLineArgumentParser(
        prog="python -m research.oracle",
        description="Compute the best eigen-kernel model of a virtual-bench dataset's "
                    "simulator (docs/compare.md): the operator oracle (least squares over the "
                    "dataset's scene distribution, noise-free; --nonneg: over non-negative "
                    "kernels, the estimand of psfkit fit-pairs' default) or the PSF oracle "
                    "(grid fit of the noise-free node PSFs).")
    p.add_argument("data", help="virtual-bench dataset folder (ekdun make-dataset)")
    p.add_argument("--out", required=True, help="kernel file to write (.npz)")
    p.add_argument("--kind", choices=("operator", "psf"), default="operator",
                   help="operator oracle (default) or PSF oracle")
    add_debug_option(p)
    p.add_argument("--basis", default="paper",
                   help="weight basis: paper (default), ek (= paper) or any weight basis of "
                        "psfkit.weights")
    p.add_argument("--convention", choices=("sensor", "source"), default="sensor",
                   help="where the weights live (default sensor, as fit-pairs)")
    p.add_argument("--nonneg", action=argparse.BooleanOptionalAction, default=True,
                   help="operator oracle over non-negative kernels (default), the estimand of "
                        "psfkit fit-pairs' default fit (projected Newton-CG to convergence); "
                        "--no-nonneg gives the unconstrained oracle that make-dataset writes")
    p.add_argument("--oracle-scenes", type=flag("--oracle-scenes"), default=0,
                   help="scenes of the operator oracle (default the dataset's: its "
                        "--oracle-scenes, else 4 x its training pairs, at least 128)")
    p.add_argument("--start", metavar="FILE.npz",
                   help="warm-start the operator oracle from these kernels (e.g. the "
                        "dataset's unconstrained oracle for --nonneg): same result, fewer "
                        "iterations")
    p.add_argument("--no-convergence-check", action="store_true",
                   help="skip the solve on half the scenes (its agreement with the full "
                        "solve is recorded; it costs about half the time again)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run_oracle)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``python -m research.oracle`` with ``argv``; returns the exit code (bad input: one
    line, status 2, as the product's commands)."""
    return run_cli("research.oracle", build_parser(), argv)


def run_oracle(args: argparse.Namespace) -> int:
    from ekdun.data.bench_spec import VirtualBenchSpec
    from ekdun.data.oracle import operator_oracle, psf_oracle
    from ekdun.data.virtual_bench import read_manifest
    from psfkit.io import OutputTransaction
    from psfkit.kernelfile import load_kernels, save_kernels
    from psfkit.weights import get_basis

    out = Path(args.out)
    if out.suffix != ".npz":
        raise InvalidInputError(f"{out}: kernel files are .npz")
    manifest = read_manifest(args.data)
    if manifest is None or "spec" not in manifest:
        raise InvalidInputError(f"{args.data}: not a virtual-bench dataset (no manifest.json "
                                "from ekdun make-dataset)")
    try:
        spec = VirtualBenchSpec.from_dict(manifest["spec"])
    except (TypeError, ConfigurationError) as exc:   # an edited manifest: name it
        raise InvalidInputError(f"{Path(args.data) / 'manifest.json'}: spec: {exc}") from None
    # an unknown basis is one line, before any work
    basis = get_basis(BASIS_ALIASES.get(args.basis, args.basis))
    if args.kind == "psf" and (args.start or args.oracle_scenes or args.no_convergence_check):
        raise InvalidInputError("--start, --oracle-scenes and --no-convergence-check apply to "
                                "--kind operator only")
    start = None
    if args.start:
        seed = load_kernels(args.start)
        want = (basis.n_kernels, 3, *spec.sensor_shape)
        if (seed.basis, seed.convention) != (basis.name, args.convention) or \
                tuple(seed.kernels.shape) != want:
            raise InvalidInputError(
                f"{args.start}: --start must be {basis.name}/{args.convention} kernels of shape "
                f"{want}, got {seed.basis}/{seed.convention} {tuple(seed.kernels.shape)}")
        start = seed.kernels
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        staged = outputs.file(out)          # checked before the (long) solve
        if args.kind == "psf":
            result = psf_oracle(spec, args.convention, basis.name)
        else:
            result = operator_oracle(spec, args.convention, basis.name,
                                     n_scenes=args.oracle_scenes or spec.oracle_scenes or None,
                                     check_convergence=not args.no_convergence_check,
                                     nonneg=args.nonneg, start=start,
                                     progress=not args.quiet)
        save_kernels(staged, result.model)
    rec = result.record
    line = f"{rec['kind']} oracle ({basis.name}, {args.convention}): {out}"
    if args.kind == "operator":
        line += (f"; {rec['n_scenes']} scenes, CG {rec['iterations']} iterations to "
                 f"{rec['relative_residual']:.1e}")
        if "projected" in rec:
            pr = rec["projected"]
            line += (f", Newton {pr['iterations']} steps to KKT {pr['kkt_residual']:.1e}"
                     + ("" if pr["converged"] else " (NOT converged)"))
        line += f"; predicts its scenes to {100 * rec['relative_prediction_error']:.2f} %"
    print(line, file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
