"""The argument parser of both command-line interfaces: usage errors are one line."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from psfkit.io.validation import escape_line


class OneLineArgumentParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line on stderr (exit status 2), like
    every other error of the command-line interfaces; ``--help`` still shows the usage."""

    def _get_value(self, action: argparse.Action, arg_string: str) -> Any:
        # Every free-text argument of both CLIs is a path or a name: an empty one (``--out ''``)
        # would read as "not given" (``if args.out``) or as the current folder (``Path('')``),
        # so it is a bad argument, refused here for every argument of every command.
        if arg_string == "" and action.type is None and not action.choices:
            raise argparse.ArgumentError(action, "must not be empty")
        return super()._get_value(action, arg_string)

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.split()[0]   # "psfkit: error: ..." like every other error
        sys.stderr.write(escape_line(f"{command}: error: {message} (see {self.prog} --help)")
                         + "\n")
        sys.exit(2)
