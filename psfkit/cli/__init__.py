"""Command-line interface of psfkit: a thin layer over the library (``psfkit --help``)."""

from psfkit.cli.main import main, run_cli

__all__ = ["main", "run_cli"]
