"""Entry point of the ``psfkit`` command and the error handling shared with ``ekdun``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from psfkit import __version__
from psfkit.errors import PsfkitError


def run_cli(prog: str, parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> int:
    """Parse ``argv`` and run the chosen sub-command.

    Expected failures (:class:`~psfkit.errors.PsfkitError`, file-system errors) become one
    line on stderr and exit status 2; Ctrl-C gives status 130. Outputs are written
    atomically by the library, so a failed command leaves no partial files.
    """
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except PsfkitError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"{prog}: error: {where}{exc.strerror or exc}", file=sys.stderr)
    except MemoryError:
        print(f"{prog}: error: out of memory (try --downsample or a smaller input)",
              file=sys.stderr)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    return 2


def build_parser() -> argparse.ArgumentParser:
    from psfkit.cli import (
        characterize_cmd,
        compare_cmd,
        fit_cmd,
        inspect_cmd,
        pairs_cmd,
        simulate_cmd,
    )

    parser = argparse.ArgumentParser(
        prog="psfkit",
        description="Characterize the shift-variant PSF of a lensless (diffuser) camera.")
    parser.add_argument("--version", action="version", version=f"psfkit {__version__}")
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")
    simulate_cmd.register(sub)
    inspect_cmd.register(sub)
    characterize_cmd.register(sub)
    fit_cmd.register(sub)
    pairs_cmd.register(sub)
    compare_cmd.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``psfkit`` with ``argv`` (default: the process arguments); returns the exit code."""
    return run_cli("psfkit", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
