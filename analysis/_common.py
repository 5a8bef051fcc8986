"""Shared plumbing of the analysis scripts (argument errors → one line, atomic outputs).

Not a package and not installed: each script puts this folder on ``sys.path`` itself.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from psfkit.cli.main import run_cli
from psfkit.io.jsonable import jsonable


def run(parser: argparse.ArgumentParser, body: Callable[[argparse.Namespace], int],
        argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run ``body``; expected failures become one line on stderr and exit
    status 2 (the psfkit CLI's handling, :func:`psfkit.cli.main.run_cli`)."""
    parser.set_defaults(func=body)
    return run_cli(Path(sys.argv[0]).name, parser, argv)


def write_json(path: Path, doc: dict[str, Any]) -> None:
    path.write_text(json.dumps(jsonable(doc), indent=1) + "\n", encoding="utf-8")
