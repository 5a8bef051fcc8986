"""Fig. 7 of the paper (learned Kbase, Kv, Kh and Kv − Kbase, Kh − Kbase), with the
learned-vs-measured comparison the paper only shows.

Usage::

    python analysis/fig7_learned_kernels.py LEARNED GRID --out DIR [--initial K.npz]

``LEARNED`` is a kernel file (``kernels_learned.npz``, ``ekdun export-kernels``) or an EK-DUN
checkpoint (``RUN_DIR/checkpoint.pt``, or the run folder), whose kernels are exported with
:func:`ekdun.training.export_kernels`; for a checkpoint, ``--initial`` defaults to its seed
kernels (:func:`ekdun.training.initial_kernels`).
Writes ``DIR/figures/fig7.png|pdf`` (the paper's layout, learned kernels alone; ``fig7_zoom``
the central part of the caustic), ``fig7_starts`` (measured modes and the learned kernels side
by side, displacement fields as arrows, for this start and, with ``--one-psf RUN``, a second
model trained from one PSF), ``DIR/fig7_caption.md`` (the numbers: displacement correlation,
difference NCC, pedestal share of the kernel change, principal angles), and the comparison of
:func:`psfkit.compare.compare_kernels` (as ``psfkit compare``, with the kernel-change split):
``DIR/compare.json``, ``DIR/compare.html``, ``DIR/figures/``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import run
from _fig7_starts import caption, figure_starts, start_numbers

from psfkit.compare import check_learned, compare_kernels, load_grid
from psfkit.compare_report import write_comparison
from psfkit.figures import figure_kernels
from psfkit.kernelfile import KernelModel, load_kernels


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


def main(args: argparse.Namespace) -> int:
    learned, initial = load_learned(args.learned)
    check_learned(learned, args.learned)
    if args.initial:
        initial = load_kernels(args.initial)
    grid = load_grid(args.grid)
    comparison = compare_kernels(learned, grid, initial=initial, progress=not args.quiet)
    names = list(learned.kernel_names)
    # the paper's figure: the learned kernels alone
    starts = {args.label: comparison}
    if args.one_psf:
        other, other_initial = load_learned(args.one_psf)
        check_learned(other, args.one_psf)
        starts[args.one_psf_label] = compare_kernels(other, comparison.measured,
                                                     initial=other_initial)
    numbers = {label: start_numbers(c) for label, c in starts.items()}
    text = caption(numbers)
    paper = [("fig7", figure_kernels(learned.kernels, names, "learned eigen-kernels")),
             ("fig7_zoom", figure_kernels(learned.kernels, names,
                                          "learned eigen-kernels (zoom)", zoom=0.3)),
             ("fig7_starts", figure_starts(starts))]
    out = write_comparison(comparison, args.out, overwrite=args.overwrite,
                           extra_figures=paper)
    tmp = out / ".fig7_caption.md.tmp"
    tmp.write_text(f"**Fig. 7 (remade).** Measured modes and learned kernels; {text}\n",
                   encoding="utf-8")
    tmp.replace(out / "fig7_caption.md")
    for label, row in comparison.headline().items():
        print(f"{label}: " + ", ".join(f"{k} {v:.3f}" if v == v else f"{k} n/a"
                                       for k, v in row.items()))
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
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


if __name__ == "__main__":
    sys.exit(run(parser(), main))
