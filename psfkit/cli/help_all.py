"""``--help`` shows what a command needs first; ``--help-all`` also the flags marked advanced
(:func:`mark_advanced`), whose help text is kept on the action (:data:`ADVANCED_HELP`)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

#: Attribute of an advanced flag's action that keeps its help while ``--help`` hides it.
ADVANCED_HELP = "advanced_help"


class _HelpAll(argparse.Action):
    """Show the advanced flags' help again, print the full help and exit (status 0)."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, _option_string: str | None = None) -> None:
        for action in parser._actions:
            if hasattr(action, ADVANCED_HELP):
                action.help = getattr(action, ADVANCED_HELP)
        parser.print_help()
        parser.exit()


def add_command(sub: argparse._SubParsersAction, name: str, summary: str, description: str,
                advanced: bool = True) -> argparse.ArgumentParser:
    """The parser of command ``name``: ``summary`` in the list of commands, ``description`` atop
    its ``--help`` and, with ``advanced`` flags, ``--help-all`` listed first."""
    if advanced:
        description += " --help-all lists the advanced flags."
    parser = sub.add_parser(name, help=summary, description=description)
    if advanced:
        add_help_all(parser)
    return parser


def add_help_all(parser: argparse.ArgumentParser) -> None:
    """Add ``--help-all`` to ``parser`` (call it first, so that it is listed beside ``-h``)."""
    parser.add_argument("--help-all", action=_HelpAll, nargs=0, dest=argparse.SUPPRESS,
                        default=argparse.SUPPRESS,
                        help="show this help with every flag, the advanced ones too")


def mark_advanced(parser: argparse.ArgumentParser, names: Sequence[str]) -> None:
    """Hide the flags ``names`` of ``parser`` from ``--help`` (``KeyError`` for an unknown one);
    ``--help-all`` shows them."""
    actions = {option: action for action in parser._actions
               for option in action.option_strings}
    for name in names:
        action = actions[name]
        setattr(action, ADVANCED_HELP, action.help)
        action.help = argparse.SUPPRESS


def is_advanced(action: argparse.Action) -> bool:
    """Whether ``action`` is a flag that only ``--help-all`` lists."""
    return hasattr(action, ADVANCED_HELP)
