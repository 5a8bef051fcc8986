"""An eigen-kernel oracle of an existing virtual-bench dataset, as a kernel file (a thin layer
over :mod:`research.oracles`); ``ekdun oracle`` until issue 44, a research instrument now.

    python -m research.oracle DATASET --out oracle.npz [--kind operator|psf] [--no-nonneg]
    python -m research.oracle DATASET --write-dataset [--oracle-scenes N]

``--write-dataset`` writes the unconstrained operator and PSF oracles of both conventions into
the dataset, ``DATASET/oracle/``, and lists them in its manifest (what the studies, Fig. 7 and
notebook 03 read; ``ekdun make-dataset`` wrote them until issue 44); a dataset that already
has them, of the same scenes, is left as it is. ``--out`` computes any oracle with other
settings, and the *non-negative* operator oracle, the estimand of ``psfkit fit-pairs``'
default (non-negative) fit, which a dataset does not carry (minutes at 128², the cost of a
fit-pairs).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ekdun.errors import InvalidInputError
from ekdun.flag_ranges import flag
from psfkit.cli import run_cli
from psfkit.cli.main import add_debug_option
from psfkit.cli.parser import OneLineArgumentParser
from psfkit.cli.vocabulary import BASIS_ALIASES


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m research.oracle``."""
    p = OneLineArgumentParser(
        prog="python -m research.oracle",
        description="Compute the best eigen-kernel model of a virtual-bench dataset's "
                    "simulator (research/compare/README.md): the operator oracle (least "
                    "squares over the dataset's scene distribution, noise-free; --nonneg: "
                    "over non-negative kernels, the estimand of psfkit fit-pairs' default) or "
                    "the PSF oracle (grid fit of the noise-free node PSFs).")
    p.add_argument("data", help="virtual-bench dataset folder (ekdun make-dataset)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--out", help="kernel file to write (.npz)")
    what.add_argument("--write-dataset", action="store_true",
                      help="write the unconstrained operator and PSF oracles of both "
                           "conventions into DATASET/oracle/ and list them in its manifest "
                           "(kept if already there, of the same scenes)")
    p.add_argument("--kind", choices=("operator", "psf"), default="operator",
                   help="operator oracle (default) or PSF oracle")
    add_debug_option(p)
    p.add_argument("--basis", default="paper",
                   help="weight basis: paper (default), ek (= paper) or any weight basis of "
                        "psfkit.forward.weights")
    p.add_argument("--convention", choices=("sensor", "source"), default="sensor",
                   help="where the weights live (default sensor, as fit-pairs)")
    p.add_argument("--nonneg", action=argparse.BooleanOptionalAction, default=True,
                   help="operator oracle over non-negative kernels (default), the estimand of "
                        "psfkit fit-pairs' default fit (projected Newton-CG to convergence); "
                        "--no-nonneg gives the unconstrained oracle that make-dataset writes")
    p.add_argument("--oracle-scenes", type=flag("--oracle-scenes"), default=0,
                   help="scenes of the operator oracle (default the dataset's: those of the "
                        "oracle it lists, else 4 x its training pairs, at least 128)")
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
    if args.write_dataset:
        return run_write_dataset(args)
    from psfkit.forward.kernelfile import load_kernels, save_kernels
    from psfkit.forward.weights import get_basis
    from psfkit.io import OutputTransaction
    from research.oracles import (
        dataset_oracle_scenes,
        dataset_spec,
        operator_oracle,
        psf_oracle,
    )

    out = Path(args.out)
    if out.suffix != ".npz":
        raise InvalidInputError(f"{out}: kernel files are .npz")
    manifest, spec = dataset_spec(args.data)
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
            n = args.oracle_scenes or dataset_oracle_scenes(manifest)
            result = operator_oracle(spec, args.convention, basis.name, n_scenes=n,
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


#: the flags that ``--write-dataset`` does not take (it writes the unconstrained oracles of
#: both conventions, paper basis: what the studies read), with their defaults
_NOT_WITH_WRITE = {"--kind": "operator", "--basis": "paper", "--convention": "sensor",
                   "--nonneg": True, "--start": None, "--no-convergence-check": False,
                   "--overwrite": False}


def run_write_dataset(args: argparse.Namespace) -> int:
    """``--write-dataset``: the dataset's own oracles, into ``DATASET/oracle/``."""
    from psfkit.io.atomic import protected_inputs
    from research.oracles import write_dataset_oracles

    given = [name for name, default in _NOT_WITH_WRITE.items()
             if getattr(args, name.lstrip("-").replace("-", "_")) != default]
    if given:
        raise InvalidInputError(f"--write-dataset writes the unconstrained paper-basis oracles "
                                f"of both conventions; it does not take {', '.join(given)}")
    # DATASET is the input and, for this one folder and its manifest, the output: written in
    # place on purpose (atomically), so the runner's input protection is lifted for it
    with protected_inputs(()):
        record, computed = write_dataset_oracles(args.data, n_scenes=args.oracle_scenes or None,
                                                 progress=not args.quiet)
    n = record["files"]["source"]["operator_record"]["n_scenes"]
    print(f"oracles ({record['basis']}, source and sensor): {Path(args.data) / 'oracle'}; "
          f"{n} scenes" + ("" if computed else " (already there, kept)"), file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
