"""research/size_report.py (issue 44's size targets): each line is counted once, in the kind it
is, the raw count is ``wc -l``'s, and the CLI surface is read from real argparse help screens."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from research.size_report import PACKAGES, commands_of, file_lines, line_counts, visible_flags

SOURCE = '''"""Module docstring,
two lines."""

# a comment
import os


def f(x):
    """One-line docstring."""
    y = "# not a comment"  # trailing comment
    return x + len(y)


class C:
    """Docstring
    over

    four lines (one blank)."""
'''


def test_file_lines_sorts_every_line_into_one_kind() -> None:
    counts = file_lines(SOURCE)
    assert counts["raw"] == SOURCE.count("\n") == 18
    # the blank line inside C's docstring is blank, not docstring
    assert counts == {"raw": 18, "blank": 6, "comment": 1, "docstring": 6, "code": 5}
    assert sum(v for k, v in counts.items() if k != "raw") == len(SOURCE.splitlines())


def test_line_counts_match_wc_on_a_tree(tmp_path) -> None:
    for package in PACKAGES:
        (tmp_path / package / "sub").mkdir(parents=True)
        (tmp_path / package / "a.py").write_text(SOURCE)
        (tmp_path / package / "sub" / "b.py").write_text("x = 1\n" * 40)
    report = line_counts(tmp_path)
    files = [str(p) for p in tmp_path.rglob("*.py")]
    wc = subprocess.run(["wc", "-l", *files], capture_output=True, text=True, check=True)
    assert report["lines"]["raw"] == int(wc.stdout.split()[-2])
    assert report["raw_per_package"] == {p: 58 for p in PACKAGES}
    assert report["largest_file"]["lines"] == 40


def _helps() -> tuple[str, str]:
    top = argparse.ArgumentParser(prog="tool")
    sub = top.add_subparsers(title="commands", metavar="COMMAND")
    run = sub.add_parser("run-all", help="run")
    sub.add_parser("info", help="info")
    run.add_argument("input")
    run.add_argument("--out", "-o")
    run.add_argument("--quiet", action="store_true", help="no output")
    run.add_argument("--hidden", help=argparse.SUPPRESS)
    run.add_argument("--help-all", action="store_true")
    return top.format_help(), run.format_help()


def test_commands_and_visible_flags_from_argparse_help() -> None:
    top, run = _helps()
    assert commands_of(top) == ["run-all", "info"]
    # positionals, suppressed flags, -h and --help-all are not counted; a flag with a short
    # spelling counts once
    assert visible_flags(run) == ["--out", "--quiet"]


def _listed_commands() -> set[str]:
    """The subcommands each CLI's parser lists in its help (hidden deprecated ones are not)."""
    from ekdun.cli import build_parser as ekdun_parser
    from psfkit.cli.main import build_parser as psfkit_parser

    listed = set()
    for package, build in (("psfkit", psfkit_parser), ("ekdun", ekdun_parser)):
        sub = next(a for a in build()._actions if isinstance(a, argparse._SubParsersAction))
        listed |= {f"{package} {choice.dest}" for choice in sub._choices_actions}
    return listed


def test_the_repository_report(tmp_path) -> None:
    """On this checkout: the raw count is wc's, the commands are the parsers' listed ones."""
    out = tmp_path / "size.json"
    subprocess.run([sys.executable, "-m", "research.size_report", "--json", str(out)],
                   capture_output=True, text=True, check=True)
    report = json.loads(out.read_text())
    root = Path(__file__).resolve().parents[2]
    files = [str(p) for package in PACKAGES for p in (root / package).rglob("*.py")]
    wc = subprocess.run(["wc", "-l", *files], capture_output=True, text=True, check=True)
    assert report["lines"]["raw"] == int(wc.stdout.split()[-2])
    assert set(report["cli"]["flags_per_command"]) == _listed_commands()
    assert report["cli"]["visible_flags"] == sum(report["cli"]["flags_per_command"].values())
