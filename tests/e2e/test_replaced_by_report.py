"""``psfkit register``, ``mae`` and ``warp`` are parts of ``psfkit report`` (issue 44, item 4).

They are no longer listed by ``psfkit --help``; for one release the old spellings run as before
and then print one line naming ``psfkit report`` and where its outputs carry their numbers.
That line is checked against the truth: the numbers each old command wrote are the ones
``report`` writes at the places the line names. ``report --help`` shows at most 12 flags;
``--help-all`` shows every one, and every flag still works.
"""

from __future__ import annotations

import argparse
import csv
import json
import re

import pytest

from psfkit.cli import main
from psfkit.cli.characterize_cmd import REPORT_ADVANCED, replaced_note
from psfkit.cli.main import build_parser

pytestmark = pytest.mark.e2e

REPLACED = ("register", "mae", "warp")


def _listed_commands(help_text: str) -> list[str]:
    section = help_text[help_text.index("commands:"):]
    return re.findall(r"^ {4}([a-z][a-z-]+)", section, flags=re.M)


def test_replaced_commands_are_not_listed(capsys):
    assert main(["--help"]) == 0
    listed = _listed_commands(capsys.readouterr().out)
    assert "report" in listed and "fit-eigen" in listed
    assert not set(REPLACED) & set(listed), listed
    assert len(listed) == 7


def _flag_lines(help_text: str) -> list[str]:
    """The flags of a help screen: the lines that start with an option."""
    return re.findall(r"^ {2}(-[-\w]+)", help_text, flags=re.M)


def test_report_help_shows_at_most_12_flags_and_help_all_every_one(capsys):
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args(["report", "--help"])
    assert done.value.code == 0
    short = capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args(["report", "--help-all"])
    assert done.value.code == 0
    full = capsys.readouterr().out
    shown, every = _flag_lines(short), _flag_lines(full)
    assert len(shown) <= 12 and "--help-all" in shown and "--out" in shown
    assert not set(REPORT_ADVANCED) & set(shown), shown
    assert not any(name in short for name in REPORT_ADVANCED)   # nor in the usage line
    # --help-all: every flag of the command (hidden deprecated aliases aside)
    sub = next(a for a in build_parser()._actions
               if isinstance(a, argparse._SubParsersAction)).choices["report"]
    flags = {a.option_strings[0] for a in sub._actions
             if (a.option_strings and a.help != argparse.SUPPRESS)
             or set(a.option_strings) & set(REPORT_ADVANCED)}
    assert set(every) == flags and set(REPORT_ADVANCED) <= set(every)
    assert len(every) == len(shown) + len(REPORT_ADVANCED)


def test_advanced_flags_still_work():
    args = build_parser().parse_args([
        "report", "G", "--out", "D", "--method", "tvl1", "--mae-smoothing", "0",
        "--upsample", "20", "--hot-pixel-sigma", "5", "--normalization", "sum",
        "--min-ncc", "0.3"])
    assert (args.method, args.mae_smoothing, args.upsample, args.hot_pixel_sigma,
            args.normalization, args.min_ncc) == ("tvl1", 0.0, 20, 5.0, "sum", 0.3)


def _notes(err: str) -> list[str]:
    return [line for line in err.strip().splitlines() if "psfkit report" in line]


def test_old_spellings_run_and_report_carries_their_numbers(grid_3x3, tmp_path, capsys):
    """Each old command: its usual output, then one note (the last line on stderr) naming
    ``psfkit report``; the numbers it wrote are report's, where the note says."""
    written = {}
    for command, suffix in zip(REPLACED, (".json", ".csv", ".json"), strict=True):
        out = tmp_path / f"{command}{suffix}"
        assert main([command, str(grid_3x3), "--out", str(out), "--quiet"]) == 0
        captured = capsys.readouterr()
        assert _notes(captured.err) == [replaced_note(command)]
        assert captured.err.strip().splitlines()[-1] == replaced_note(command)
        assert {"register": "shift du (px):", "mae": "MAE vs the centre PSF",
                "warp": "residual displacement rms"}[command] in captured.out
        written[command] = out
    report = tmp_path / "report"
    assert main(["report", str(grid_3x3), "--out", str(report), "--per-channel",
                 "--quiet"]) == 0
    captured = capsys.readouterr()
    assert _notes(captured.err) == []
    # --per-channel: report prints each channel's shifts too (as register did)
    assert "channel 2 shift dv (px):" in captured.out

    doc = json.loads((report / "results.json").read_text())
    by_cell = {(p["row"], p["col"]): p for p in doc["positions"]}
    with open(report / "positions.csv", newline="") as fh:
        rows = {(int(r["row"]), int(r["col"])): r for r in csv.DictReader(fh)}
    assert all(p["channel_shifts"] is not None and len(p["channel_shifts"]) == 3
               for p in doc["positions"])

    registered = json.loads(written["register"].read_text())
    assert registered["shift_map"]["magnification"] == pytest.approx(
        doc["shift_map"]["magnification"], rel=1e-9)
    for p in registered["positions"]:
        assert p["shift_px"] == pytest.approx(by_cell[p["row"], p["col"]]["shift_px"],
                                              abs=1e-9)
    with open(written["mae"], newline="") as fh:
        for r in csv.DictReader(fh):
            mine = rows[int(r["row"]), int(r["col"])]
            for column in ("mae", "mae_gain_compensated"):
                assert float(r[column]) == pytest.approx(float(mine[column]), rel=1e-9)
    warped = json.loads(written["warp"].read_text())
    assert warped["warp_growth"] == doc["warp_growth"]
    for p in warped["positions"]:
        if p["warp"] is None:
            assert by_cell[p["row"], p["col"]]["warp"] is None
            continue
        mine = by_cell[p["row"], p["col"]]["warp"]
        for key in ("residual_rms", "anisotropy"):   # None where not measured (the centre)
            assert (p["warp"][key] is None) == (mine[key] is None), key
            if mine[key] is not None:
                assert p["warp"][key] == pytest.approx(mine[key], rel=1e-9), key


def test_a_failing_old_spelling_is_still_one_line(grid_3x3, tmp_path, capsys):
    assert main(["mae", str(grid_3x3), "--out", str(tmp_path / "m.txt"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "must end in .json or .csv" in err[0]
