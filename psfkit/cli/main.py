"""Entry point of the ``psfkit`` command and the error handling shared with ``ekdun``."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
from collections.abc import Iterator, Sequence

from psfkit import __version__
from psfkit.errors import PsfkitError


class Terminated(KeyboardInterrupt):
    """SIGTERM, SIGHUP or SIGINT (Ctrl-C), raised in the main thread so that it unwinds like
    Ctrl-C: every ``with`` block of an output transaction removes its temporaries."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextlib.contextmanager
def terminate_like_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM, SIGHUP and SIGINT raise :class:`Terminated` (main thread
    only).

    A signal that lands inside C code may surface as another exception (an extension module
    being imported turns it into ``ImportError``); once a signal was received, whatever
    propagates becomes :class:`Terminated`, so the exit status still says why.
    """
    received: list[int] = []

    def handler(signum: int, frame: object) -> None:
        received.append(signum)
        raise Terminated(signum)

    previous = {}
    try:
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
            previous[sig] = signal.signal(sig, handler)
    except ValueError:   # not the main thread: leave the signals alone
        pass
    try:
        yield
    except Exception as exc:
        if received:
            raise Terminated(received[0]) from exc
        raise
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def run_cli(prog: str, parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> int:
    """Parse ``argv`` and run the chosen sub-command.

    Expected failures (:class:`~psfkit.errors.PsfkitError`, file-system errors) become one
    line on stderr and exit status 2; Ctrl-C gives status 130, SIGTERM 143 (128 + signal
    number), after the temporaries of unfinished outputs have been removed. Outputs are
    written through :class:`~psfkit.io.atomic.OutputTransaction`, so a failed command leaves
    no partial files.
    """
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help(sys.stderr)
        return 2
    try:
        with terminate_like_interrupt():
            return int(args.func(args) or 0)
    except PsfkitError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"{prog}: error: {where}{exc.strerror or exc}", file=sys.stderr)
    except MemoryError:
        print(f"{prog}: error: out of memory (try --downsample or a smaller input)",
              file=sys.stderr)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        print(f"{prog}: interrupted ({signal.Signals(signum).name}); unfinished outputs "
              "removed", file=sys.stderr)
        return 128 + int(signum)
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
