"""Shared body of ``table1.py`` and ``table2.py``: evaluate runs (or read an existing
``results.json``) with :mod:`ekdun.evaluation` and write one table.

Not a package and not installed: the scripts put this folder on ``sys.path`` themselves.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from ekdun.errors import InvalidInputError
from ekdun.evaluation import (
    LPIPSMetric,
    evaluate_checkpoints,
    read_results,
    render_table,
    write_results,
    write_table,
)
from ekdun.evaluation.tables import EXPECTED, label_for, table_rows, variant_of
from psfkit.io import atomic_directory


def missing_rows(results: list[dict[str, Any]], which: str) -> list[str]:
    """Labels of the paper's rows of table ``which`` that ``results`` lack."""
    rows = table_rows(results, which)
    if which == "table1":      # its only EK-DUN row is last-2, whatever its label says
        have = {label_for(str(r.get("model")), "last-2") for r in rows if not variant_of(r)}
    else:
        have = {str(r.get("label")) for r in rows}
    return [label for label in EXPECTED[which] if label not in have]


def make_table(args: argparse.Namespace, which: str) -> int:
    """Evaluate ``args.runs`` on ``args.data`` (or read ``args.results``) and write table
    ``which`` (``"table1"`` or ``"table2"``) into the folder ``args.out``, atomically.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments of :func:`parser`.
    which : {"table1", "table2"}
        The table.

    Returns
    -------
    int
        Exit status (0).

    Raises
    ------
    InvalidInputError
        Neither or both of run folders and ``--results``; runs without ``--data``; no row of
        the table in the results.
    """
    if bool(args.runs) == bool(args.results):
        raise InvalidInputError("give run folders (with --data) or --results results.json, "
                                "not both or neither")
    if args.runs and not args.data:
        raise InvalidInputError("run folders need --data DATASET (the held-out pairs)")
    if args.results:
        results, notes = read_results(args.results)
        render_table(results, which, notes)          # fail before touching --out
    else:
        import torch

        torch.set_num_threads(args.threads)
        lpips = LPIPSMetric(args.lpips_weights)
        notes = [lpips.reason] if lpips.reason else []
        log = None if args.quiet else (lambda line: print(line, file=sys.stderr))
        results = evaluate_checkpoints(args.runs, args.data, lpips, args.device, log)
        render_table(results, which, notes)
    with atomic_directory(args.out, overwrite=args.overwrite) as tmp:
        write_table(tmp, results, which, notes)
        if not args.results:
            write_results(tmp, results, notes)
    print(render_table(results, which, notes).strip())
    missing = missing_rows(results, which)
    if missing:
        print(f"missing rows: {', '.join(missing)}")
    print(f"wrote {args.out}")
    return 0


def parser(which: str, doc: str) -> argparse.ArgumentParser:
    """Arguments of ``table1.py`` / ``table2.py`` (``which`` names the table in the help)."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("runs", nargs="*", metavar="RUN_DIR",
                   help="ekdun run folders (or their checkpoint.pt files)")
    p.add_argument("--data", help="held-out pairs folder, or a virtual-bench dataset "
                                  "(its test/ split)")
    p.add_argument("--results", help="an existing results.json (ekdun eval, research."
                                     "benchmark_tiny) to re-render without evaluating")
    p.add_argument("--out", required=True, help=f"output folder ({which}.md, {which}.json, "
                                                "results.json)")
    p.add_argument("--lpips-weights", help="local AlexNet weights for LPIPS "
                                           "(else $EKDUN_LPIPS_WEIGHTS; else unavailable)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no per-run lines on stderr")
    return p
