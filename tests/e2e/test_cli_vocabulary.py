"""One flag vocabulary for both command-line interfaces (issue 22, item 4).

Table-driven from :data:`psfkit.cli.vocabulary.VOCABULARY` and its extension
:data:`ekdun.cli.vocabulary.VOCABULARY`, and their ``DEPRECATED`` spellings: every sub-parser
of ``psfkit`` and ``ekdun`` is walked, and

- every option string has one meaning: the same destination, default and choices in every
  command where it appears, except the listed deprecated aliases; a vocabulary flag has exactly
  the declared ones (a per-command difference only where the vocabulary declares it);
- psfkit's tables name psfkit's flags and commands only (psfkit knows nothing of ekdun);
- ``--model`` appears nowhere except as a listed deprecated alias;
- every flag of every command is in ``docs/cli-flags.md``, with that command;
- every deprecated alias works through the real CLI and prints exactly one notice line, after
  the work (an error stays the one line on stderr);
- every retired flag (:data:`ekdun.cli.commands.RETIRED_FLAGS`: accepted, ignored) is in the
  table, and prints its note while the command does its work.

``python tests/e2e/test_cli_vocabulary.py`` prints the table of ``docs/cli-flags.md`` from the
parsers (the meanings of vocabulary flags from the vocabulary, the others from their help).
"""

from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ekdun.cli.vocabulary import DEPRECATED as EKDUN_DEPRECATED
from ekdun.cli.vocabulary import VOCABULARY
from psfkit.cli import vocabulary as psfkit_vocabulary

DEPRECATED = {**psfkit_vocabulary.DEPRECATED, **EKDUN_DEPRECATED}

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "cli-flags.md"


def _walk(parser: argparse.ArgumentParser, prog: str) -> list[tuple[str, str, argparse.Action]]:
    """``(cli, command, action)`` for every option of every sub-command (aliases of a
    sub-command, e.g. ``reconstruct-classical``, once)."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:
                    seen.add(id(sub))
                    found += [(prog, name, a) for a in sub._actions if a.option_strings]
    return found


def all_options() -> list[tuple[str, str, argparse.Action]]:
    from ekdun.cli import build_parser as ekdun_parser
    from psfkit.cli.main import build_parser as psfkit_parser

    return _walk(psfkit_parser(), "psfkit") + _walk(ekdun_parser(), "ekdun")


def hidden_commands() -> set[str]:
    """Sub-commands that ``--help`` does not list (replaced or moved, kept for one release:
    ``psfkit register``, ``mae``, ``warp``; ``ekdun oracle``, ``benchmark-tiny``)."""
    from ekdun.cli import build_parser as ekdun_parser
    from psfkit.cli.main import build_parser as psfkit_parser

    hidden = set()
    for parser in (psfkit_parser(), ekdun_parser()):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                listed = {choice.dest for choice in action._choices_actions}
                hidden |= set(action.choices) - listed
    return hidden


def _meaning(option: str, action: argparse.Action) -> tuple[Any, Any, Any]:
    return action.dest, action.default, tuple(action.choices) if action.choices else None


def test_every_option_string_has_one_meaning_in_every_command():
    options = all_options()
    # 8 psfkit + 4 ekdun user commands (issue 44: oracle and benchmark-tiny went to research/,
    # their hidden stubs take no options; register, mae and warp are replaced by report,
    # admm by reconstruct, export-kernels by train: hidden and still checked here, as they
    # still run)
    commands = {cmd for _, cmd, _ in options}
    assert commands & hidden_commands() == {"register", "mae", "warp", "admm", "export-kernels"}
    assert len(commands - hidden_commands()) == 11
    meanings: dict[str, set] = defaultdict(set)
    aliases_seen = set()
    for _cli, command, action in options:
        for option in action.option_strings:
            if (command, option) in DEPRECATED:
                aliases_seen.add((command, option))
                canonical = DEPRECATED[(command, option)]
                assert action.dest == VOCABULARY[canonical].dest, (command, option)
                assert action.help == argparse.SUPPRESS, f"{command} {option}: shown in --help"
                continue
            assert option != "--model", f"{command}: --model is only a deprecated alias"
            assert option != "--workers", f"{command}: --workers is only a deprecated alias"
            if option in VOCABULARY:
                entry = VOCABULARY[option]
                spec = entry.spec(command)
                assert action.dest == entry.dest, (command, option)
                assert action.default == spec["default"], (command, option, action.default)
                expected = tuple(spec["choices"]) if spec["choices"] else None
                assert _meaning(option, action)[2] == expected, (command, option)
            else:
                meanings[option].add(_meaning(option, action))
    assert aliases_seen == set(DEPRECATED), set(DEPRECATED) - aliases_seen
    for option, found in meanings.items():
        assert len(found) == 1, f"{option} means different things: {sorted(map(str, found))}"


def test_psfkit_knows_nothing_of_ekdun():
    """psfkit's vocabulary, deprecated spellings and numeric ranges name only psfkit's flags
    and commands; ekdun's extension keeps psfkit's meaning of every flag they share."""
    from psfkit.cli.main import build_parser as psfkit_parser
    from psfkit.io.flag_ranges import FLAGS as PSFKIT_FLAGS

    psfkit = [(cmd, action) for cli, cmd, action in all_options() if cli == "psfkit"]
    commands = {cmd for cmd, _ in psfkit}
    flags = {option for _, action in psfkit for option in action.option_strings}
    assert psfkit_parser().prog == "psfkit"
    assert set(psfkit_vocabulary.VOCABULARY) <= flags, set(psfkit_vocabulary.VOCABULARY) - flags
    for entry in psfkit_vocabulary.VOCABULARY.values():
        assert set(entry.per_command) <= commands, (entry.name, set(entry.per_command) - commands)
        ekdun_entry = VOCABULARY[entry.name]
        assert (ekdun_entry.dest, ekdun_entry.default, ekdun_entry.choices, ekdun_entry.kind) \
            == (entry.dest, entry.default, entry.choices, entry.kind), entry.name
        for cmd, spec in entry.per_command.items():
            assert ekdun_entry.per_command[cmd] == spec, (entry.name, cmd)
    assert {cmd for cmd, _ in psfkit_vocabulary.DEPRECATED} <= commands
    assert {cmd for cmd, _ in psfkit_vocabulary.RETIRED} <= commands
    numeric = {option for _, action in psfkit if getattr(action.type, "flag_range", None)
               for option in action.option_strings[:1]}
    assert {key.split()[-1] for key in PSFKIT_FLAGS} <= numeric, \
        {key.split()[-1] for key in PSFKIT_FLAGS} - numeric


def test_shared_flags_where_the_vocabulary_says():
    """Device, AMP and channel order where images are read; --network where one is chosen."""
    where = defaultdict(set)
    for _cli, command, action in all_options():
        for option in action.option_strings:
            where[option].add(command)
    assert where["--device"] == {"train", "eval", "reconstruct", "make-dataset"}
    assert where["--amp"] == {"train", "reconstruct"}
    assert {"fit-pairs", "eval-model", "train", "eval", "reconstruct", "admm"} \
        <= where["--channel-order"]
    assert where["--basis"] == {"fit-pairs", "fit-eigen"}
    assert where["--network"] == {"train"}
    assert where["--loader-workers"] == {"train"}


def _doc_rows() -> dict[str, str]:
    """``flag -> commands cell`` of the table in docs/cli-flags.md."""
    rows = {}
    text = DOC.read_text(encoding="utf-8")
    for line in text[text.index("## Every flag"):].splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 4 and cells[0].startswith("`--"):
            for name in re.findall(r"`(--[a-z0-9-]+)`", cells[0]):
                rows[name] = cells[-1]
    return rows


def test_every_flag_of_both_clis_is_in_the_docs_table():
    from ekdun.cli.commands import RETIRED_FLAGS
    from tests.helpers.cli import full_help

    rows = _doc_rows()
    missing = []
    for cli, command, action in all_options():
        if full_help(action) == argparse.SUPPRESS and (command, action.option_strings[0]) \
                not in DEPRECATED and (command, action.option_strings[0]) not in RETIRED_FLAGS:
            continue
        for option in action.option_strings:
            if option in ("-h", "--help"):
                continue
            cell = rows.get(option)
            if cell is None or not re.search(rf"\b{re.escape(command)}\b", cell):
                missing.append(f"{cli} {command} {option}")
    assert not missing, f"not in {DOC.name}: {missing}"
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    contract = (REPO / "docs" / "inputs-and-errors.md").read_text(encoding="utf-8")
    assert "cli-flags.md" in readme and "cli-flags.md" in contract


# ------------------------------------------------------------------ deprecated aliases, run


def _one_notice(capsys, alias: str, canonical: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    notices = [line for line in err if "deprecated" in line]
    assert notices == [f"note: {alias} is deprecated here, use {canonical}"], err
    assert err[-1] == notices[0], "the notice comes after the command's own lines"
    return notices[0]


def test_fit_pairs_model_is_basis(tiny_data, tmp_path, capsys):
    from psfkit.cli import main
    from psfkit.forward.kernelfile import load_kernels

    pairs, _ = tiny_data
    out = tmp_path / "ek.npz"
    assert main(["fit-pairs", str(pairs), "--model", "ek", "--out", str(out),
                 "--iterations", "2", "--projected-iterations", "2", "--quiet"]) == 0
    _one_notice(capsys, "--model", "--basis")
    model = load_kernels(out)
    # the convention is chosen by held-out error (the default auto), and recorded
    assert model.basis == "paper"
    assert model.convention == model.provenance["convention_choice"]["chosen"]


def test_an_error_stays_the_one_line(tiny_data, tmp_path, capsys):
    from psfkit.cli import main

    pairs, _ = tiny_data
    assert main(["fit-pairs", str(pairs), "--model", "zernike", "--out",
                 str(tmp_path / "k.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--basis" in err[0] and "zernike" in err[0], err


def test_register_workers_is_threads(grid_3x3, capsys):
    from psfkit.cli import main

    assert main(["register", str(grid_3x3), "--workers", "1", "--quiet"]) == 0
    _one_notice(capsys, "--workers", "--threads")


def test_train_model_and_workers_are_network_and_loader_workers(tiny_data, tmp_path, capsys):
    from ekdun.cli import main

    pairs, kernels = tiny_data
    run = tmp_path / "run"
    assert main(["train", str(pairs), str(run), "--model", "updn", "--kernels", str(kernels),
                 "--epochs", "1", "--batch-size", "4", "--iterations", "1", "--threads", "1",
                 "--device", "cpu", "--quiet"]) == 0
    _one_notice(capsys, "--model", "--network")
    from ekdun.nets.checkpoint import load_checkpoint

    assert load_checkpoint(run / "checkpoint.pt")["metadata"]["model"] == "updn"
    # --workers: DataLoader workers, as before (they only act off the device: checked parsed)
    from ekdun.cli import build_parser

    args = build_parser().parse_args(["train", str(pairs), str(run), "--psf", "p.npy",
                                      "--workers", "3"])
    assert args.loader_workers == 3 and args.deprecation_notices == [
        "note: --workers is deprecated here, use --loader-workers"]
    assert VOCABULARY["--loader-workers"].default == 2


def test_admm_tau_is_tv(tmp_path, capsys):
    from ekdun.cli import main

    rng = np.random.default_rng(0)
    psf = np.zeros((32, 32, 3), np.float32)
    psf[14:18, 14:18] = 1.0
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "y.npy", rng.random((32, 32, 3), dtype=np.float32))
    assert main(["admm", str(tmp_path / "psf.npy"), str(tmp_path / "y.npy"), "--out",
                 str(tmp_path / "x.npy"), "--tau", "1e-3", "--iterations", "3", "--threads",
                 "1", "--background", "none", "--quiet"]) == 0
    # admm itself is deprecated (issue 44): its note follows the flag's, both after the work
    from ekdun.cli.classical_cmd import deprecated_note

    err = capsys.readouterr().err.strip().splitlines()
    assert err[-2:] == ["note: --tau is deprecated here, use --tv", deprecated_note("admm")]
    assert (tmp_path / "x.npy").is_file()


# ------------------------------------------------------------------ the docs table


def test_make_dataset_retired_oracle_flags_note_and_make_the_dataset(tmp_path, capsys):
    """``--no-oracle`` and ``--oracle-scenes`` (make-dataset wrote the oracles until issue 44):
    accepted and ignored, one note each after the work; the dataset is made, without oracles;
    a bad value is still refused in one line."""
    from ekdun.cli import main
    from ekdun.cli.commands import RETIRED_FLAGS
    from ekdun.data.virtual_bench import read_manifest

    out = tmp_path / "data"
    small = ["--sensor", "32", "32", "--n-train", "2", "--n-test", "1", "--grid", "3", "3",
             "--threads", "1", "--quiet"]
    assert main(["make-dataset", str(out), *small, "--no-oracle", "--oracle-scenes", "48"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [RETIRED_FLAGS[("make-dataset", "--no-oracle")][1],
                   RETIRED_FLAGS[("make-dataset", "--oracle-scenes")][1]]
    assert all("research.oracle DATASET --write-dataset" in line for line in err)
    manifest = read_manifest(out)
    assert manifest is not None and len(manifest["files"]) > 0
    assert "oracle" not in manifest and "oracle" not in manifest["spec"]
    assert not (out / "oracle").exists() and len(list((out / "train" / "scene").iterdir())) == 2
    # without the flags: no note; the same spec, so the dataset is reused as it is
    stamp = (out / "manifest.json").stat().st_mtime_ns
    assert main(["make-dataset", str(out), *small]) == 0
    assert capsys.readouterr().err == ""
    assert (out / "manifest.json").stat().st_mtime_ns == stamp
    assert main(["make-dataset", str(tmp_path / "bad"), *small, "--oracle-scenes", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--oracle-scenes" in err[0] and not (tmp_path / "bad").exists()


def flag_table() -> str:
    """The Markdown table of docs/cli-flags.md, from the parsers and the vocabulary.

    A flag that only ``--help-all`` lists is marked *(advanced)* after its command; the
    commands that ``--help`` does not list (replaced, kept for one release) *(deprecated)*.
    """
    from ekdun.cli.commands import RETIRED_FLAGS as EKDUN_RETIRED
    from psfkit.cli.help_all import is_advanced
    from psfkit.cli.vocabulary import RETIRED as PSFKIT_RETIRED
    from tests.helpers.cli import full_help

    # both CLIs' retired flags (accepted, ignored, one note): (nargs, note, ...) alike
    RETIRED_FLAGS = {**EKDUN_RETIRED, **PSFKIT_RETIRED}
    hidden = hidden_commands()
    rows: dict[str, dict[str, Any]] = {}
    for cli, command, action in all_options():
        names = [o for o in action.option_strings if o not in ("-h", "--help")]
        if not names:
            continue
        deprecated = (command, names[0]) in DEPRECATED
        key = names[0]
        row = rows.setdefault(key, {"commands": [], "help": None, "default": None,
                                    "deprecated": [], "names": names})
        marks = [m for m, on in (("deprecated", command in hidden),
                                 ("advanced", is_advanced(action))) if on]
        row["commands"].append(f"{cli} {command}" + (f" *({', '.join(marks)})*" if marks
                                                      else ""))
        if deprecated:
            row["deprecated"].append(f"{command}: use `{DEPRECATED[(command, key)]}`")
            continue
        if (command, key) in RETIRED_FLAGS:
            row["retired"] = RETIRED_FLAGS[(command, key)][1].split("ignored: ", 1)[1]
            continue
        # the help of a listed command, where one has the flag (a replaced command's may
        # speak of its own outputs)
        if full_help(action) and (row["help"] is None
                                  or (row.get("from_hidden") and command not in hidden)):
            row["help"] = full_help(action)
            row["default"] = action.default
            row["from_hidden"] = command in hidden
    lines = ["| flag | meaning | default | commands |", "|---|---|---|---|"]
    for key in sorted(rows):
        row = rows[key]
        if key in VOCABULARY:
            meaning, default = VOCABULARY[key].meaning, VOCABULARY[key].default_text
        elif row.get("retired"):
            meaning, default = f"deprecated, ignored: {row['retired']}", "-"
        elif row["help"] is None:
            meaning, default = "deprecated alias (" + "; ".join(row["deprecated"]) + ")", "-"
        else:
            meaning = re.sub(r"\s*\(default[^)]*\)", "", row["help"])
            stated = re.search(r"\(default:? ([^)]*)\)", row["help"])
            default = str(row["default"]) \
                if row["default"] not in (None, False, argparse.SUPPRESS) \
                else stated.group(1) if stated else "-"
        meaning = meaning.replace("|", "\\|")
        flags = ", ".join(f"`{name}`" for name in row["names"])
        lines.append(f"| {flags} | {meaning} | {default} | {', '.join(row['commands'])} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":   # pragma: no cover
    print(flag_table(), end="")
