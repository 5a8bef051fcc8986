"""Entry point of the ``psfkit`` command and the error handling shared with ``ekdun``."""

from __future__ import annotations

import argparse
import contextlib
import functools
import gc
import json
import logging
import os
import signal
import sys
import warnings
import zipfile
from collections.abc import Iterator, Sequence

from psfkit import __version__
from psfkit.cli.allocator import reuse_freed_memory
from psfkit.cli.parser import OneLineArgumentParser
from psfkit.cli.run_file import parse_args
from psfkit.cli.vocabulary import deprecation_notices
from psfkit.errors import InvalidInputError, PsfkitError
from psfkit.io.atomic import protected_inputs
from psfkit.io.images import collected_log
from psfkit.io.temps import public_name
from psfkit.io.validation import escape_line


def split_debug(prog: str, argv: Sequence[str] | None) -> tuple[bool, list[str]]:
    """Whether ``--debug`` (anywhere before ``--``) or ``PSFKIT_DEBUG=1`` / ``EKDUN_DEBUG=1``
    asks for tracebacks, and the arguments without it."""
    args = sys.argv[1:] if argv is None else list(argv)
    end = args.index("--") if "--" in args else len(args)
    kept = [a for a in args[:end] if a != "--debug"] + args[end:]
    env = os.environ.get(f"{prog.upper()}_DEBUG", "") or os.environ.get("PSFKIT_DEBUG", "")
    return len(kept) < len(args) or env not in ("", "0"), kept


def close_progress_bars() -> None:
    """Close every progress bar still open (tqdm keeps them in class-level sets), so that
    none is redrawn after a failed command's final line on stderr."""
    std = sys.modules.get("tqdm.std")
    if std is None:   # no bar was ever made
        return
    classes, bars = [std.tqdm], []
    while classes:    # tqdm.auto's class and others keep their own set of instances
        cls = classes.pop()
        classes += cls.__subclasses__()
        bars += list(cls.__dict__.get("_instances", ()))
    for bar in bars:
        with contextlib.suppress(Exception):   # a bar that cannot draw any more is closed
            bar.close()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _is_allocation_error(exc: BaseException) -> bool:
    """torch reports failed allocations as RuntimeError subclasses (OutOfMemoryError) or as a
    RuntimeError whose text says so; numpy as MemoryError or ValueError('array is too big')."""
    text = str(exc)
    return (type(exc).__name__ == "OutOfMemoryError" or "DefaultCPUAllocator" in text
            or "out of memory" in text or "array is too big" in text
            or "Maximum allowed size exceeded" in text)


def error_line(prog: str, exc: BaseException) -> tuple[str, int]:
    """The one line and the exit status for a command's exception: bad input gives status 2,
    anything else is an internal error (status 1); control characters are escaped and a
    temporary output is named as the output it would have become."""
    line, status = _error_line(prog, exc)
    return escape_line(public_name(line)), status


def _error_line(prog: str, exc: BaseException) -> tuple[str, int]:
    if isinstance(exc, PsfkitError):
        return f"{prog}: error: {exc}", 2
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        return f"{prog}: error: {where}{exc.strerror or _first_line(exc)}", 2
    if isinstance(exc, MemoryError) or _is_allocation_error(exc):
        return (f"{prog}: error: out of memory ({_first_line(exc)[:120]}); an input declares "
                "sizes larger than this machine can hold"), 2
    if isinstance(exc, RecursionError):
        return f"{prog}: error: an input is nested too deeply to be read", 2
    if isinstance(exc, (json.JSONDecodeError, zipfile.BadZipFile, EOFError)):
        return f"{prog}: error: an input file is malformed ({_first_line(exc)})", 2
    if isinstance(exc, (ValueError, TypeError)):
        return (f"{prog}: error: invalid value ({_first_line(exc)[:200]}); if the inputs are "
                f"valid this is a bug: please report it (run with --debug for details)"), 2
    return (f"{prog}: internal error ({type(exc).__name__}: {_first_line(exc)[:200]}); this is "
            f"a bug, please report it with the command line (--debug or "
            f"{prog.upper()}_DEBUG=1 prints the traceback)"), 1


#: Destinations of the free-text arguments that name a command's outputs; every other
#: free-text argument (a grid, pairs, kernel file, checkpoint, measurement...) is an input
#: that no output may replace (:func:`psfkit.io.atomic.protected_inputs`).
OUTPUT_ARGUMENTS = frozenset({"out", "figures", "report", "run_dir"})


def input_paths(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[str]:
    """The values of ``args`` for free-text arguments (paths and names) of ``parser`` and its
    sub-commands, other than :data:`OUTPUT_ARGUMENTS`."""
    dests: set[str] = set()
    parsers = [parser]
    while parsers:
        p = parsers.pop()
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                parsers += list(action.choices.values())
            elif action.type is None and not action.choices and action.nargs != 0:
                dests.add(action.dest)
    values: list[str] = []
    for dest in sorted(dests - OUTPUT_ARGUMENTS):
        value = getattr(args, dest, None)
        values += [value] if isinstance(value, str) else [
            v for v in (value if isinstance(value, list) else ()) if isinstance(v, str)]
    return values


class Terminated(KeyboardInterrupt):
    """SIGTERM, SIGHUP or SIGINT, raised in the main thread to unwind like Ctrl-C."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextlib.contextmanager
def terminate_like_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM, SIGHUP and SIGINT raise :class:`Terminated` (main thread
    only); once a signal was received, whatever propagates (a signal inside C code may surface
    as another exception) becomes :class:`Terminated`."""
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


@contextlib.contextmanager
def quiet_libraries() -> Iterator[None]:
    """Within the block, Python warnings and library logging are collected instead of
    printed, so that a command's stderr holds its own lines only."""
    with collected_log(level=logging.WARNING), warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        yield


@contextlib.contextmanager
def destructor_errors_of_an_interruption() -> Iterator[list[bool]]:
    """Within the block, errors raised by destructors (``Exception ignored in ...``) are held
    back (garbage is collected before it ends); dropped if the caller set ``flag[0]`` (the
    command was interrupted: half-built objects), else printed as usual."""
    interrupted = [False]
    held: list[object] = []
    previous = sys.unraisablehook
    sys.unraisablehook = held.append
    try:
        yield interrupted
    finally:
        gc.collect()
        sys.unraisablehook = previous
        for report in () if interrupted[0] else held:
            previous(report)


def run_cli(prog: str, parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> int:
    """Parse ``argv`` and run the chosen sub-command; returns the exit status.

    Every failure is one line on stderr (:func:`error_line`: status 2 for bad input, 1 for an
    internal error); Ctrl-C / SIGTERM give 128 + the signal number after unfinished outputs
    are removed; a closed stdout gives 141 quietly. ``--debug`` shows tracebacks instead.
    """
    debug, argv = split_debug(prog, argv)
    try:
        args = parse_args(parser, argv)   # with the command's --config run file, if any
    except SystemExit as exc:  # usage errors (one line, status 2) and --help / --version
        return exc.code if isinstance(exc.code, int) else 2
    if not hasattr(args, "func"):
        parser.print_help(sys.stderr)
        return 2
    reuse_freed_memory()         # fewer page faults in the full-resolution passes
    with destructor_errors_of_an_interruption() as interrupted:
        try:
            with terminate_like_interrupt(), protected_inputs(input_paths(parser, args)), \
                    (contextlib.nullcontext() if debug else quiet_libraries()):
                status = int(args.func(args) or 0)
        except KeyboardInterrupt as exc:
            interrupted[0] = not debug
            signum = int(getattr(exc, "signum", signal.SIGINT))
        except Exception as exc:
            if debug:
                raise
            return _failure(prog, exc)
        else:
            # after the work, so that an error stays the one line on stderr
            for line in deprecation_notices(args):
                print(line, file=sys.stderr)
            return status
    close_progress_bars()   # the line below is the last one on stderr
    print(f"{prog}: interrupted ({signal.Signals(signum).name}); unfinished outputs removed",
          file=sys.stderr)
    return 128 + signum


def _failure(prog: str, exc: Exception) -> int:
    """Report a failed command in one line on stderr; its exit status."""
    if isinstance(exc, BrokenPipeError) and _stdout_closed():
        # the reader of stdout went away (``psfkit register GRID | head -1``): stop
        # quietly, as Unix tools do on SIGPIPE; outputs are committed before the summary
        return 128 + signal.SIGPIPE
    close_progress_bars()
    line, status = error_line(prog, exc)
    print(line, file=sys.stderr)
    return status


def _stdout_closed() -> bool:
    """Whether stdout is a pipe whose reader has gone; then stdout is pointed at /dev/null,
    so that Python's last flush does not complain on stderr."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        closed = any(events & select.POLLERR for _, events in poller.poll(0))
        if closed:
            os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
        return closed
    except (OSError, ValueError, AttributeError):   # no real file descriptor (captured)
        return False


def add_debug_option(parser: argparse.ArgumentParser) -> None:
    """``--debug`` in the top-level help (:func:`run_cli` takes it anywhere)."""
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error (before or after the "
                             "command)")


#: Commands that left the product for the source repository's research/ folder
#: (docs/migration.md), kept hidden for one release to say where they went.
MOVED = {"compare": "python -m research.compare"}


def register_moved(sub: argparse._SubParsersAction, prog: str, moved: dict[str, str]) -> None:
    """Add the commands ``moved`` (``name: replacement``) to ``sub``, hidden: each stops with one
    line naming its replacement, status 2 (research/ is not installed, so it cannot run it)."""
    for name, replacement in moved.items():
        # no help=: hidden; every argument is taken as it comes and ignored (type=str: not a
        # path for the checks of free-text inputs, which would name it first)
        p = sub.add_parser(name, add_help=False, prefix_chars="\0")
        p.add_argument("rest", nargs="*", type=str)
        p.set_defaults(func=functools.partial(_run_moved, f"{prog} {name}", replacement))


def _run_moved(command: str, replacement: str, _args: argparse.Namespace) -> int:
    raise InvalidInputError(
        f"`{command}` is no longer a user command: it is a research study, run "
        f"`{replacement} ...` from a source checkout (docs/migration.md)")


def build_parser() -> argparse.ArgumentParser:
    from psfkit.cli import (
        characterize_cmd,
        eval_cmd,
        fit_cmd,
        inspect_cmd,
        pairs_cmd,
        simulate_cmd,
    )

    parser = OneLineArgumentParser(
        prog="psfkit",
        description="Characterize the shift-variant PSF of a lensless (diffuser) camera.")
    parser.add_argument("--version", action="version", version=f"psfkit {__version__}")
    add_debug_option(parser)
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")
    # the order of ``psfkit --help``
    for module in (simulate_cmd, inspect_cmd, characterize_cmd, fit_cmd, pairs_cmd, eval_cmd):
        module.register(sub)
    register_moved(sub, "psfkit", MOVED)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``psfkit`` with ``argv`` (default: the process arguments); returns the exit code."""
    return run_cli("psfkit", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
