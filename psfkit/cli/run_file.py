"""``--config RUN.toml``: a command's settings from a TOML run file.

Flat ``key = value`` settings keyed by the command's long flag names without dashes
(``tikhonov = 1e-3``, ``nonneg = false``, ``holdout = ["im65"]``); every value goes through
the command's own parser, so bad ones are its one-line errors, prefixed by file and key.
The command line overrides the file. A command opts in with :func:`add_config_option` and
records what was used (:func:`run_file_record`) with its outputs.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from psfkit.cli.help_all import is_advanced

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 reads TOML with the tomli backport
    import tomli as tomllib

#: Namespace attribute holding what the run file set (:func:`run_file_record`).
RUN_FILE = "run_file"
#: Attribute that marks the ``--config`` action of a command.
_MARK = "reads_run_file"
#: Largest run file read (bytes).
MAX_RUN_FILE_BYTES = 1 << 20


def add_config_option(parser: argparse.ArgumentParser, example: str, where: str
                      ) -> argparse.Action:
    """Add ``--config RUN.toml`` to ``parser`` (a command); ``example`` is one line of a run
    file of that command, ``where`` the output that records the settings."""
    action = parser.add_argument(
        "--config", metavar="RUN.toml",
        help=f"read settings from this TOML file, one line per flag of this command without "
             f"its dashes (--help-all lists them), e.g. {example}; flags given on the command "
             f"line override the file; {where} records the settings used")
    setattr(action, _MARK, True)
    return action


def run_file_record(args: argparse.Namespace) -> dict[str, Any] | None:
    """``{"path", "settings", "overridden"}`` of the run file of ``args`` (resolved path,
    ``{flag: value}`` as parsed, flags the command line overrode), or ``None``."""
    return getattr(args, RUN_FILE, None)


def parse_args(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace:
    """``parser.parse_args(argv)``, with the settings of the command's ``--config`` file
    appended before any ``--``, each joined to its flag (``--tikhonov=0.001``); a flag the
    command line also gives is left out (not merged)."""
    argv = list(argv)
    found = _command(parser, argv)
    if found is None:
        return parser.parse_args(argv)
    command, start = found
    given, path = _scan(command, argv[start:])
    if path is None:
        return parser.parse_args(argv)
    tokens: list[str] = []
    settings: dict[str, Any] = {}
    overridden: list[str] = []
    for key, action, value in _settings(command, path):
        switch_pair = isinstance(action, argparse.BooleanOptionalAction)
        name = action.option_strings[0] if switch_pair else _long_name(key)
        if action in given:
            overridden.append(name)
            continue
        new, parsed = _tokens(command, path, key, action, value)
        tokens += new
        settings[name] = parsed
    end = argv.index("--", start) if "--" in argv[start:] else len(argv)
    args = parser.parse_args(argv[:end] + tokens + argv[end:])
    setattr(args, RUN_FILE, {"path": str(Path(path).resolve()), "settings": settings,
                             "overridden": overridden})
    return args


def _command(parser: argparse.ArgumentParser, argv: list[str]
             ) -> tuple[argparse.ArgumentParser, int] | None:
    """The (sub-)parser that takes ``--config`` and where its arguments start in ``argv``."""
    start = 0
    while True:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            break
        index = next((i for i in range(start, len(argv))
                      if not argv[i].startswith("-") and argv[i] in subs[0].choices), None)
        if index is None:
            return None
        parser, start = subs[0].choices[argv[index]], index + 1
    if any(getattr(a, _MARK, False) for a in parser._actions):
        return parser, start
    return None


def _resolve(command: argparse.ArgumentParser, token: str) -> argparse.Action | None:
    """The action of an option token as argparse resolves it (``--opt=v``, unique prefix)."""
    option = token.split("=", 1)[0]
    actions = command._option_string_actions
    if option in actions:
        return actions[option]
    if command.allow_abbrev and option.startswith("--"):
        matches = {a for name, a in actions.items() if name.startswith(option)}
        if len(matches) == 1:
            return matches.pop()
    return None


def _scan(command: argparse.ArgumentParser, argv: list[str]
          ) -> tuple[set[argparse.Action], str | None]:
    """The actions ``argv`` gives (before a ``--``) and the value of its last ``--config``."""
    given: set[argparse.Action] = set()
    path = None
    end = argv.index("--") if "--" in argv else len(argv)
    for i, token in enumerate(argv[:end]):
        action = _resolve(command, token) if token.startswith("-") and len(token) > 1 else None
        if action is None:
            continue
        given.add(action)
        if getattr(action, _MARK, False) and "=" in token:
            path = token.split("=", 1)[1]
        elif getattr(action, _MARK, False) and i + 1 < end:
            path = argv[i + 1]
    return given, path or None


def _long_name(key: str) -> str:
    return "--" + key.replace("_", "-")


def _read(command: argparse.ArgumentParser, path: str) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:   # a run file is a few lines: never read a huge one
            data = fh.read(MAX_RUN_FILE_BYTES + 1)
        if len(data) > MAX_RUN_FILE_BYTES:
            command.error(f"{path}: the run file is larger than {MAX_RUN_FILE_BYTES} bytes "
                          "(a run file holds a few settings)")
        return tomllib.loads(data.decode("utf-8"))
    except RecursionError:
        command.error(f"{path}: the run file is nested too deeply to be read")
    except OSError as exc:
        command.error(f"{path}: cannot read the run file ({exc.strerror or exc})")
    except UnicodeDecodeError:
        command.error(f"{path}: the run file is not TOML (not UTF-8 text)")
    except tomllib.TOMLDecodeError as exc:
        command.error(f"{path}: the run file is not valid TOML ({exc})")
    raise AssertionError("unreachable")   # parser.error exits


def _settings(command: argparse.ArgumentParser, path: str
              ) -> list[tuple[str, argparse.Action, Any]]:
    """``(key, action, value)`` of every key of the file, each a flag of ``command``."""
    positionals = {name for a in command._actions if not a.option_strings
                   for name in (a.dest, str(a.metavar or "").lower()) if name}
    seen: dict[argparse.Action, str] = {}
    found = []
    for key, value in _read(command, path).items():
        if isinstance(value, dict):
            command.error(f"{path}: key '{key}' is a table; a run file holds key = value "
                          "settings")
        name = _long_name(key)
        action = command._option_string_actions.get(name)
        if key.replace("-", "_") in positionals and action is None:
            command.error(f"{path}: key '{key}' is an argument of the command, not a "
                          "setting: give it on the command line")
        listed = action is not None and (action.help != argparse.SUPPRESS
                                         or is_advanced(action))
        if not listed or action.dest == argparse.SUPPRESS or getattr(action, _MARK, False) \
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            command.error(f"{path}: unknown key '{key}' (the keys are the long flag names "
                          f"of {command.prog}; --help-all lists them)")
        if action in seen:
            command.error(f"{path}: keys '{seen[action]}' and '{key}' set the same flag")
        seen[action] = key
        found.append((key, action, value))
    return found


def _tokens(command: argparse.ArgumentParser, path: str, key: str, action: argparse.Action,
            value: Any) -> tuple[list[str], Any]:
    """The command-line tokens of one setting, and its value as the parser reads it."""
    name = _long_name(key)
    if action.nargs == 0:   # a switch: true / false
        if not isinstance(value, bool):
            command.error(f"{path}: key '{key}' is a switch: true or false, got {value!r}")
        if isinstance(action, argparse.BooleanOptionalAction):
            on = value == (name == action.option_strings[0])
            return [action.option_strings[0 if on else 1]], on
        return ([name] if value else []), value
    repeatable = isinstance(action, argparse._AppendAction) or action.nargs in ("+", "*")
    values = value if isinstance(value, list) and repeatable else [value]
    if not values:
        command.error(f"{path}: key '{key}' is an empty list")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (str, int, float)):
            command.error(f"{path}: key '{key}' takes a value (a string or a number), got "
                          f"{v!r}")
    texts = [str(v) for v in values]
    parsed = [_parsed(command, path, key, action, t) for t in texts]
    if isinstance(action, argparse._AppendAction):
        return [f"{name}={t}" for t in texts], parsed
    if repeatable:
        return [name, *texts], parsed
    return [f"{name}={texts[0]}"], parsed[0]


def _parsed(command: argparse.ArgumentParser, path: str, key: str, action: argparse.Action,
            text: str) -> Any:
    """``text`` converted and checked as the parser does for ``action`` (same error)."""
    try:
        value = command._get_value(action, text)
        command._check_value(action, value)
    except argparse.ArgumentError as exc:
        command.error(f"{path}: key '{key}': {exc}")
    return value
