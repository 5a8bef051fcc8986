"""One flag vocabulary: every flag used by more than one command is declared once
(:data:`VOCABULARY`: meaning, destination, default, choices, and where a command deliberately
differs) and added with :func:`add_flag`. Deprecated spellings (:data:`DEPRECATED`) and
retired flags (:data:`RETIRED`) are hidden and print one note after the command's work.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from psfkit.io.flag_ranges import flag
from psfkit.io.read_options import CHANNEL_ORDERS

#: ``namespace`` attribute that collects the notices of deprecated spellings.
NOTICES = "deprecation_notices"

#: Values of ``--basis`` that name another (``ek`` is the paper's basis).
BASIS_ALIASES = {"ek": "paper"}


@dataclass(frozen=True)
class SharedFlag:
    """One flag of the vocabulary; ``per_command`` maps a command to the keys (``default``,
    ``choices``, ``meaning``, ``default_text``) in which it deliberately differs."""

    name: str
    dest: str
    meaning: str
    default_text: str
    default: Any = None
    choices: tuple[str, ...] | None = None
    kind: str = "text"          # "text" or "number" (type from the flag ranges)
    metavar: str | None = None
    parse: Callable[[str], Any] | None = None   # argparse type of a "text" flag
    per_command: dict[str, dict[str, Any]] = field(default_factory=dict)

    def spec(self, command: str) -> dict[str, Any]:
        """``default``, ``choices``, ``meaning`` and ``default_text`` of this flag in
        ``command``."""
        spec = {"default": self.default, "choices": self.choices, "meaning": self.meaning,
                "default_text": self.default_text}
        spec.update(self.per_command.get(command, {}))
        return spec


_PAIR_NAMES = "pairs (file stems, e.g. im65; comma-separated, repeatable)"
_CONVENTION = "where the weights of {} eigen-kernel model live: sensor (the paper's Eq. 7), source"

VOCABULARY: dict[str, SharedFlag] = {f.name: f for f in (
    SharedFlag("--basis", "basis",
               # the general meaning (docs/cli-flags.md); each command's help says its own
               "weight basis of the model: si (one PSF, fit-pairs only), ek (= paper: Kbase, "
               "Kv, Kh) or any weight basis of psfkit.forward.weights (fit-eigen: also auto)",
               "si (fit-pairs), paper (fit-eigen)", default="si",
               per_command={
                   "fit-eigen": {"default": "paper", "meaning":
                                 "weight basis of the eigen-kernel model: ek (= paper: Kbase, "
                                 "Kv, Kh), another weight basis of psfkit.forward.weights, "
                                 "or auto"},
                   "fit-pairs": {"meaning":
                                 "the model to fit: si (one shift-invariant PSF), ek (= paper: "
                                 "Kbase, Kv, Kh) or another weight basis of "
                                 "psfkit.forward.weights"}}),
    SharedFlag("--convention", "convention",
               "where the weights of an eigen-kernel model live: sensor (the paper's Eq. 7) "
               "or source (also auto = the lower held-out error)",
               "sensor (fit-pairs: auto)", default="sensor", choices=("sensor", "source"),
               # fit-eigen: unset = sensor, or with --basis auto the verdict's convention
               per_command={"fit-pairs": {"choices": ("sensor", "source", "auto"),
                                          "default": "auto", "meaning": _CONVENTION.format("an")
                                          + ", or auto (the lower held-out error)"},
                            "fit-eigen": {"choices": ("sensor", "source", "auto"),
                                          "default": None, "meaning": _CONVENTION.format("the")
                                          + ", or auto (the lower cross-validated error)"}}),
    SharedFlag("--threads", "threads", "CPU threads", "2", kind="number", metavar="N",
               # one meaning per command, each help line describes only its own
               per_command={cmd: {"meaning": "PSF positions processed at the same time",
                                  "default_text": "2"} for cmd in ("report", "register", "mae",
                                                                   "warp")}),
    SharedFlag("--channel-order", "channel_order",
               "channel order of the .npy/TIFF files on disk (RGB or BGR)",
               "the data's declaration (pairs.json, the DLMD layout: BGR) or the model's "
               "record, else RGB", choices=CHANNEL_ORDERS),
    SharedFlag("--seed", "seed", "random seed", "0 (simulate-grid, demo: the --bench-config "
               "file's, else 0)", default=0, kind="number",
               per_command={"simulate-grid": {"default": None}, "demo": {"default": None}}),
    SharedFlag("--holdout", "holdout",
               f"{_PAIR_NAMES} left out of the fit; eval-model: the pairs the model was not "
               "fitted on, where its file does not record them", "-", metavar="NAME[,NAME]",
               per_command={
                   "fit-pairs": {"meaning": f"{_PAIR_NAMES} left out of the fit"},
                   "eval-model": {"meaning": f"{_PAIR_NAMES} the model was not fitted on, where "
                                             "its file does not record them"}}),
    SharedFlag("--out", "out", "where the outputs go (a file or folder, per command)",
               "required, or none (demo: psfkit-demo)",
               per_command={"demo": {"default": "psfkit-demo"}}),
)}

#: Deprecated spellings: ``(command, alias) -> canonical flag``. An alias keeps the old meaning
#: for its command (same destination) and prints one notice after the work.
DEPRECATED: dict[tuple[str, str], str] = {
    ("fit-pairs", "--model"): "--basis",
    ("register", "--workers"): "--threads",
    ("mae", "--workers"): "--threads",
    ("warp", "--workers"): "--threads",
    ("report", "--workers"): "--threads",
}


def command_name(parser: argparse.ArgumentParser) -> str:
    """The sub-command of a sub-parser (``"psfkit fit-pairs"`` -> ``"fit-pairs"``)."""
    return parser.prog.split()[-1]


def add_flag(parser: argparse.ArgumentParser | argparse._ArgumentGroup, name: str,
             command: str, note: str = "", *, vocabulary: Mapping[str, SharedFlag] = VOCABULARY,
             deprecated: Mapping[tuple[str, str], str] = DEPRECATED,
             number_type: Callable[[str, str], Callable[[str], Any]] = flag,
             **extra: Any) -> argparse.Action:
    """Add the vocabulary's flag ``name`` to ``parser`` for ``command``, and its deprecated
    spellings; ``note`` replaces the default's text in the help, ``extra`` passes other
    ``add_argument`` keywords. Another CLI passes its own tables (``vocabulary``,
    ``deprecated``, ``number_type``)."""
    entry = vocabulary[name]
    spec = entry.spec(command)
    kwargs: dict[str, Any] = {"dest": entry.dest, "default": spec["default"]}
    if spec["choices"] is not None:
        kwargs["choices"] = spec["choices"]
    if entry.kind == "number":
        kwargs["type"] = number_type(name, command)
    elif entry.parse is not None:
        kwargs["type"] = entry.parse
    if entry.metavar:
        kwargs["metavar"] = entry.metavar
    kwargs["help"] = f"{spec['meaning']} (default: {note or spec['default_text']})"
    kwargs.update(extra)
    action = parser.add_argument(name, **kwargs)
    for (cmd, alias), canonical in deprecated.items():
        if cmd == command and canonical == name:   # hidden, same destination, type, choices
            parser.add_argument(alias, action=_Notice, dest=action.dest, type=action.type,
                                note=f"note: {alias} is deprecated here, use {name}",
                                choices=action.choices, metavar=action.metavar,
                                default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    return action


def record_notice(namespace: argparse.Namespace, line: str) -> None:
    """Keep ``line`` (once) among the notes printed after the command's work."""
    notices = list(getattr(namespace, NOTICES, None) or [])
    if line not in notices:
        notices.append(line)
    setattr(namespace, NOTICES, notices)


class _Notice(argparse.Action):
    """A deprecated spelling (stores like its canonical flag) or a retired flag (``dest``
    suppressed: stores nothing); either records its ``note``, printed after the work."""

    def __init__(self, option_strings: Sequence[str], dest: str, note: str = "",
                 **kwargs: Any) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.note = note

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, _option_string: str | None = None) -> None:
        if self.dest != argparse.SUPPRESS:
            setattr(namespace, self.dest, values)
        record_notice(namespace, self.note)


#: Retired flags: ``(command, flag) -> (nargs, note, choices)``. Accepted (a value is still
#: checked against ``choices``) and ignored for one release, hidden from ``--help``; the note is
#: printed once the command has done its work (``docs/migration.md``).
RETIRED: dict[tuple[str, str], tuple[int, str, tuple[str, ...] | None]] = {
    ("fit-pairs", "--nonneg-solver"): (
        1, "note: --nonneg-solver is deprecated and ignored: fit-pairs has one non-negative "
           "solver, projected Newton-CG to convergence (docs/migration.md)",
        ("auto", "fista", "newton")),
    ("fit-pairs", "--energy"): (
        1, "note: --energy is deprecated and ignored: fit-pairs leaves each kernel's energy "
           "to the non-negative least squares (docs/migration.md)",
        ("free", "fit", "base")),
}


def add_retired(parser: argparse.ArgumentParser, command: str,
                table: Mapping[tuple[str, str], tuple[int, str, tuple[str, ...] | None]]
                = RETIRED, value_type: Callable[[str], Callable[[str], Any]] | None = None
                ) -> None:
    """Add ``command``'s retired flags of ``table`` to ``parser``, hidden; ``value_type(flag)``,
    where given, still checks a retired flag's value."""
    for (cmd, name), (nargs, note, choices) in table.items():
        if cmd == command:
            parser.add_argument(name, action=_Notice, note=note, nargs=nargs,
                                choices=choices,
                                type=value_type(name) if value_type and nargs else None,
                                dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                                help=argparse.SUPPRESS)


def deprecation_notices(args: argparse.Namespace) -> list[str]:
    """The notice lines of the deprecated spellings ``args`` was parsed from."""
    return list(getattr(args, NOTICES, None) or [])
