"""Table 1 of the paper: EK-DUN (last-2) against Le-ADMM-U and UPDN (PSNR, SSIM, LPIPS,
parameters, runtime, peak memory).

Usage::

    python analysis/table1.py RUN_DIR [RUN_DIR ...] --data DATASET --out DIR
    python analysis/table1.py --results results.json --out DIR

Evaluates the runs on the held-out pairs with :func:`ekdun.evaluation.evaluate_checkpoints`
(as ``ekdun eval``), or re-renders an existing ``results.json``, and writes ``DIR/table1.md``,
``DIR/table1.json`` (and ``DIR/results.json`` after an evaluation).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import run
from _tables import make_table, parser

if __name__ == "__main__":
    sys.exit(run(parser("table1", __doc__), lambda args: make_table(args, "table1")))
