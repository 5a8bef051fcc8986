"""How big is the product? Issue 44's size targets, measured the way the issue measured them.

The issue's "product code ≤ 18,000 lines (from 22,505)" is ``wc -l`` over every ``.py`` file of
``psfkit/`` and ``ekdun/``: that count reproduces its 22,505 exactly at e757c3e, the commit it was
filed against (its 3,608 lines of ``docs/*.md`` match there too). This script prints that count
beside the non-blank, the non-comment and the docstring lines, the largest file, the user
commands and the flags each ``--help`` shows, and the lines of ``docs/*.md``.

Usage (from a checkout)::

    python -m research.size_report [--json OUT]
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

PACKAGES = ("psfkit", "ekdun")
#: An option entry of an argparse help screen: two spaces, then ``-x`` or ``--long``.
OPTION = re.compile(r"^  (-\w|--[\w-]+)")
#: A command entry of the top-level help: four spaces and a lower-case name.
COMMAND = re.compile(r"^    ([a-z][a-z-]+)\b")


def docstring_lines(source: str) -> set[int]:
    """1-based numbers of the lines that belong to a module, class or function docstring."""
    lines: set[int] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                    and isinstance(body[0].value.value, str)):
                lines.update(range(body[0].lineno, body[0].end_lineno + 1))
    return lines


def file_lines(source: str) -> dict[str, int]:
    """``raw`` (``wc -l``: newlines), ``blank``, ``comment`` (only a ``#`` comment),
    ``docstring`` and ``code`` (the rest) lines of one Python source."""
    docs = docstring_lines(source)
    counts = {"raw": source.count("\n"), "blank": 0, "comment": 0, "docstring": 0, "code": 0}
    for number, line in enumerate(source.splitlines(), 1):
        text = line.strip()
        kind = ("blank" if not text else "docstring" if number in docs
                else "comment" if text.startswith("#") else "code")
        counts[kind] += 1
    return counts


def line_counts(root: Path) -> dict[str, object]:
    """Totals over :data:`PACKAGES` under ``root``, per package, and the largest file."""
    totals = dict.fromkeys(("raw", "blank", "comment", "docstring", "code"), 0)
    per_package: dict[str, int] = {}
    largest = ("", 0)
    for package in PACKAGES:
        per_package[package] = 0
        for path in sorted((root / package).rglob("*.py")):
            counts = file_lines(path.read_text(encoding="utf-8"))
            for key, value in counts.items():
                totals[key] += value
            per_package[package] += counts["raw"]
            if counts["raw"] > largest[1]:
                largest = (str(path.relative_to(root)), counts["raw"])
    return {"lines": totals, "raw_per_package": per_package,
            "largest_file": {"path": largest[0], "lines": largest[1]}}


def _help(root: Path, *args: str) -> str:
    env = dict(os.environ, COLUMNS="100", PYTHONPATH=str(root))
    done = subprocess.run([sys.executable, "-m", *args, "--help"], capture_output=True,
                          text=True, env=env, cwd=root, check=True)
    return done.stdout


def commands_of(top_help: str) -> list[str]:
    """The commands a top-level ``--help`` lists under ``commands:``."""
    section = top_help.split("commands:", 1)[-1]
    return [m.group(1) for line in section.splitlines() if (m := COMMAND.match(line))]


def visible_flags(command_help: str) -> list[str]:
    """The options one ``--help`` screen shows (``-h/--help`` and ``--help-all`` excluded)."""
    flags = [m.group(1) for line in command_help.splitlines() if (m := OPTION.match(line))]
    return [f for f in flags if f not in ("-h", "--help", "--help-all")]


def cli_surface(root: Path) -> dict[str, object]:
    """Every user command and the flags its ``--help`` shows."""
    flags: dict[str, list[str]] = {}
    for package in PACKAGES:
        for command in commands_of(_help(root, f"{package}.cli")):
            flags[f"{package} {command}"] = visible_flags(_help(root, f"{package}.cli", command))
    counts = {name: len(f) for name, f in flags.items()}
    return {"commands": len(flags), "visible_flags": sum(counts.values()),
            "most_flags": max(counts.values(), default=0), "flags_per_command": counts}


def docs_lines(root: Path) -> int:
    """Lines of the user docs, ``docs/*.md`` (``wc -l``)."""
    return sum(p.read_text(encoding="utf-8").count("\n") for p in (root / "docs").glob("*.md"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="also write the numbers to this JSON file")
    args = parser.parse_args(argv)
    root = Path(__file__).resolve().parent.parent
    report = {**line_counts(root), "cli": cli_surface(root), "docs_lines": docs_lines(root)}
    lines = report["lines"]
    print(f"product lines (wc -l, issue 44's metric): {lines['raw']}  "
          f"(code {lines['code']}, docstrings {lines['docstring']}, comments "
          f"{lines['comment']}, blank {lines['blank']})")
    print(f"largest file: {report['largest_file']['path']} "
          f"({report['largest_file']['lines']} lines)")
    cli = report["cli"]
    print(f"user commands: {cli['commands']}; visible flags: {cli['visible_flags']} "
          f"(most in one command: {cli['most_flags']})")
    for name, count in cli["flags_per_command"].items():
        print(f"  {name}: {count}")
    print(f"docs/*.md: {report['docs_lines']} lines")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
