"""Shared plumbing of the analysis scripts (argument errors → one line, atomic outputs).

``write_json`` is psfkit's (:func:`psfkit.io.jsonable.write_json`), re-exported here.

Not a package and not installed: each script puts this folder on ``sys.path`` itself.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from psfkit.cli.main import run_cli
from psfkit.io.jsonable import write_json

__all__ = ["run", "write_json"]


def run(parser: argparse.ArgumentParser, body: Callable[[argparse.Namespace], int],
        argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run ``body``; expected failures become one line on stderr and exit
    status 2 (the psfkit CLI's handling, :func:`psfkit.cli.main.run_cli`)."""
    parser.set_defaults(func=body)
    return run_cli(Path(sys.argv[0]).name, parser, argv)

