"""Command-line interface of ekdun: a thin layer over the library (``ekdun --help``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from ekdun import __version__
from psfkit.cli import run_cli
from psfkit.cli.main import add_debug_option
from psfkit.cli.parser import OneLineArgumentParser


def build_parser() -> argparse.ArgumentParser:
    from ekdun.cli import commands

    parser = OneLineArgumentParser(
        prog="ekdun",
        description="Train, evaluate and run unrolled reconstruction networks (EK-DUN, "
                    "Le-ADMM-U, UPDN) for lensless cameras.")
    parser.add_argument("--version", action="version", version=f"ekdun {__version__}")
    add_debug_option(parser)
    sub = parser.add_subparsers(title="commands", metavar="COMMAND", dest="command")
    commands.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``ekdun`` with ``argv``; returns the exit code."""
    return run_cli("ekdun", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
