"""Fig. 7 of the paper (learned Kbase, Kv, Kh and Kv − Kbase, Kh − Kbase), with the
learned-vs-measured comparison the paper only shows.

Usage::

    python analysis/fig7_learned_kernels.py LEARNED GRID --out DIR [--initial K.npz]
        [--one-psf RUN] [--oracle ORACLE.npz | --no-oracle]

``LEARNED`` is a kernel file (``kernels_learned.npz``, ``ekdun export-kernels``) or an EK-DUN
checkpoint (``RUN_DIR/checkpoint.pt``, or the run folder), whose kernels are exported with
:func:`ekdun.nets.export.export_kernels`; for a checkpoint, ``--initial`` defaults to its seed
kernels (:func:`ekdun.training.initial_kernels`).
Writes ``DIR/figures/fig7.png|pdf`` (the paper's layout, learned kernels alone; ``fig7_zoom``
the central part of the caustic), ``fig7_starts`` (measured modes and the learned kernels side
by side, displacement fields as arrows, for this start and, with ``--one-psf RUN``, a second
model trained from one PSF), ``DIR/fig7_caption.md`` (the numbers: displacement correlation,
difference NCC, pedestal share of the kernel change, principal angles), and the comparison of
:func:`research.compare.compare_kernels` (as ``python -m research.compare``, with the
kernel-change split):
``DIR/compare.json``, ``DIR/compare.html``, ``DIR/figures/``.

The oracle (virtual bench): ``--oracle ORACLE.npz`` names the best eigen-kernel model of the
simulator (``python -m research.oracle DATASET --write-dataset`` writes it,
``DATASET/oracle/paper_{source,sensor}.npz``; see research/notes/compare-studies.md). When GRID
is a virtual-bench dataset's ``grid/`` folder whose manifest lists an operator oracle of the
learned model's convention, that file is used by default (the script prints which; found with
``research.oracles.oracle_file``, from the ``research/`` folder beside this one in the
checkout; without it, or without an oracle, a note and the measured rows only);
``--no-oracle`` skips it. With an oracle, ``fig7_starts`` gains an oracle row,
and the caption, the printed numbers and ``DIR/oracle.json`` give every learned model and the
measured fit against the oracle (difference NCC, displacement correlation and end-point error,
principal angles). An explicit ``--oracle`` of another basis, convention or sensor size than
the learned model is refused in one line.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
# the comparison and the oracles are research studies (research/, not installed): this checkout's
sys.path.append(str(Path(__file__).resolve().parents[1]))

from _common import run
from _fig7_starts import caption, figure_starts, oracle_caption, start_numbers

from psfkit.errors import ModelFileError
from psfkit.forward.kernelfile import KernelModel, load_kernels
from psfkit.io.jsonable import jsonable
from psfkit.report.figures import figure_kernels
from research.compare import check_learned, compare_kernels, compare_model, load_grid
from research.compare.report import write_comparison


def load_learned(path: str) -> tuple[KernelModel, KernelModel | None]:
    """``(learned, initial)`` kernels of ``path``: a kernel file (initial ``None``), or an
    EK-DUN checkpoint / run folder (its exported kernels and its seed kernels)."""
    where = Path(path)
    if where.suffix != ".pt" and not where.is_dir():
        return load_kernels(path), None
    from ekdun.evaluation.evaluate import checkpoint_path
    from ekdun.training import export_kernels, initial_kernels, load_checkpoint

    doc = load_checkpoint(checkpoint_path(where))
    return export_kernels(doc), initial_kernels(doc)


def check_oracle(oracle: KernelModel, learned: KernelModel, where: str) -> None:
    """Refuse an oracle that cannot be the reference of ``learned`` (one line)."""
    for attr, what in (("basis", "basis"), ("convention", "convention"),
                       ("sensor_shape", "sensor")):
        mine, theirs = getattr(oracle, attr), getattr(learned, attr)
        if attr == "sensor_shape":
            mine, theirs = "x".join(map(str, mine)), "x".join(map(str, theirs))
        if mine != theirs:
            raise ModelFileError(f"{where}: oracle {what} {mine} differs from the learned "
                                 f"model's {theirs}; give the oracle of the learned model's "
                                 "dataset and convention")


def find_oracle(args: argparse.Namespace, learned: KernelModel
                ) -> tuple[KernelModel | None, str | None]:
    """``(oracle, its path)``: ``--oracle``, else the one the dataset of GRID lists for the
    learned model's convention (``(None, None)`` with a printed note when there is none)."""
    if args.no_oracle:
        return None, None
    if args.oracle:
        oracle = load_kernels(args.oracle)
        check_oracle(oracle, learned, args.oracle)
        return oracle, args.oracle
    from ekdun.data.virtual_bench import read_manifest

    grid = Path(args.grid)
    root = grid.resolve().parent
    if read_manifest(root) is None or (root / "grid").resolve() != grid.resolve():
        return None, None                       # not a virtual-bench dataset's grid
    from research.oracles import oracle_file

    path = oracle_file(root, learned.convention)
    if path is None:
        print(f"no oracle: the dataset {root} lists no {learned.convention}-side oracle "
              f"(python -m research.oracle {root} --write-dataset writes it); measured rows "
              "only")
        return None, None
    oracle = load_kernels(path)
    try:
        check_oracle(oracle, learned, str(path))
    except ModelFileError as exc:
        print(f"no oracle: {exc}")
        return None, None
    print(f"oracle: {path} (operator oracle, {learned.convention} side, from the dataset's "
          "manifest; --no-oracle skips it)")
    return oracle, str(path)


def main(args: argparse.Namespace) -> int:
    learned, initial = load_learned(args.learned)
    check_learned(learned, args.learned)
    if args.initial:
        initial = load_kernels(args.initial)
    oracle, oracle_path = find_oracle(args, learned)
    grid = load_grid(args.grid)
    comparison = compare_kernels(learned, grid, initial=initial, progress=not args.quiet)
    names = list(learned.kernel_names)
    # the paper's figure: the learned kernels alone
    starts = {args.label: comparison}
    models = {args.label: learned}
    if args.one_psf:
        other, other_initial = load_learned(args.one_psf)
        check_learned(other, args.one_psf)
        if oracle is not None:
            check_oracle(oracle, other, str(oracle_path))
        starts[args.one_psf_label] = compare_kernels(other, comparison.measured,
                                                     initial=other_initial)
        models[args.one_psf_label] = other
    numbers = {label: start_numbers(c) for label, c in starts.items()}
    text = caption(numbers)
    oracle_row = None
    vs_oracle: dict[str, dict[str, Any]] = {}
    extra: list[tuple[str, str]] = []
    if oracle is not None:
        # every model against the oracle (the reference), and the oracle's own row in the
        # figure: registered to the measured Kbase, displacements on the measured mask
        vs_oracle = {f"learned: {label}": compare_kernels(model, oracle).learned.numbers()
                     for label, model in models.items()}
        vs_oracle["measured fit"] = compare_kernels(comparison.measured.model,
                                                    oracle).learned.numbers()
        oracle_row = ("operator oracle", compare_model(oracle, comparison.measured, "oracle",
                                                       where=str(oracle_path)))
        oracle_text = oracle_caption(Path(str(oracle_path)).name, vs_oracle)
        text = f"{text} {oracle_text}"
        doc: dict[str, Any] = {"oracle": str(oracle_path), "kind": "operator",
                               "convention": oracle.convention, "vs_oracle": vs_oracle}
        extra.append(("oracle.json", json.dumps(jsonable(doc), indent=1) + "\n"))
    paper = [("fig7", figure_kernels(learned.kernels, names, "learned eigen-kernels")),
             ("fig7_zoom", figure_kernels(learned.kernels, names,
                                          "learned eigen-kernels (zoom)", zoom=0.3)),
             ("fig7_starts", figure_starts(starts, oracle_row))]
    what = "Measured modes, the operator oracle" if oracle is not None else "Measured modes"
    extra.append(("fig7_caption.md",
                  f"**Fig. 7 (remade).** {what} and learned kernels; {text}\n"))
    out = write_comparison(comparison, args.out, overwrite=args.overwrite,
                           extra_figures=paper, extra_files=extra)
    for label, row in comparison.headline().items():
        print(f"{label}: " + ", ".join(f"{k} {v:.3f}" if v == v else f"{k} n/a"
                                       for k, v in row.items()))
    for label, row in vs_oracle.items():
        print(f"vs oracle, {label}: " + ", ".join(
            f"{k} {', '.join(f'{a:.1f}' for a in v)}" if isinstance(v, list)
            else (f"{k} {v:.3f}" if v == v else f"{k} n/a") for k, v in row.items()))
    print(text)
    print(f"wrote {out}")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("learned", help="kernel file of the trained model, or its EK-DUN "
                                   "checkpoint.pt (or run folder)")
    p.add_argument("grid", help="PSF-grid folder of the same camera")
    p.add_argument("--initial", help="kernel file before training (default for a "
                                     "checkpoint: its seed kernels)")
    p.add_argument("--one-psf", help="a second model (checkpoint, run folder or kernel file) "
                                     "trained from one PSF, shown next to LEARNED")
    p.add_argument("--label", default="seeded from the measured fit",
                   help="what LEARNED started from (for the figure and caption)")
    p.add_argument("--one-psf-label", default="one PSF",
                   help="what the --one-psf model is (for the figure and caption)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--oracle", help="kernel file of the operator oracle (DATASET/oracle/"
                                        "paper_<convention>.npz, python -m research.oracle "
                                        "DATASET --write-dataset); default: the one GRID's "
                                        "virtual-bench dataset lists for the learned "
                                        "convention")
    which.add_argument("--no-oracle", action="store_true",
                       help="no oracle row or numbers, even where the dataset has one")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


if __name__ == "__main__":
    sys.exit(run(parser(), main))
