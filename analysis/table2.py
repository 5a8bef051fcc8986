"""Table 2 of the paper: where EK-DUN uses the eigen-kernel model (base only, last-2, all).

Usage::

    python analysis/table2.py RUN_DIR [RUN_DIR ...] --data DATASET --out DIR
    python analysis/table2.py --results results.json --out DIR

Evaluates the EK-DUN schedule runs on the held-out pairs with
:func:`ekdun.evaluation.evaluate_checkpoints` (as ``ekdun eval``), or re-renders an existing
``results.json``, and writes ``DIR/table2.md``, ``DIR/table2.json`` (and ``DIR/results.json``
after an evaluation).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import run
from _tables import make_table, parser

if __name__ == "__main__":
    sys.exit(run(parser("table2", __doc__), lambda args: make_table(args, "table2")))
