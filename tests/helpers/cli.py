"""The CLIs' help as ``--help-all`` shows it."""

from __future__ import annotations

import argparse

from psfkit.cli.help_all import ADVANCED_HELP


def full_help(action: argparse.Action) -> str | None:
    """The help of ``action`` as ``--help-all`` shows it (an advanced flag's too)."""
    return getattr(action, ADVANCED_HELP, action.help)
