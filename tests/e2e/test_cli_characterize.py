"""psfkit register / mae / warp / report from the command line."""

import csv
import json

import numpy as np
import pytest

from psfkit.cli import main
from psfkit.io import GridWriter


def test_report_writes_html_json_csv_and_figures(grid_3x3, tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["report", str(grid_3x3), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "shift map: magnification" in text and "report:" in text
    doc = json.loads((out / "results.json").read_text())
    assert doc["grid_shape"] == [3, 3] and len(doc["positions"]) == 9
    assert doc["shift_map"]["field_units"] == "monitor px"
    assert "normalization" in doc["conventions"]
    rows = list(csv.DictReader((out / "positions.csv").open()))
    assert len(rows) == 9 and float(rows[4]["shift_du_px"]) == 0.0
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") == 5
    for stem in ("fig2_shift_variance", "maps", "warp_summary", "warp_fields", "montage"):
        assert (out / "figures" / f"{stem}.pdf").stat().st_size > 1000
        assert (out / "figures" / f"{stem}.png").stat().st_size > 1000


@pytest.mark.parametrize("command", ["register", "mae", "warp"])
def test_numbers_to_json_and_csv(grid_3x3, tmp_path, capsys, command):
    for suffix in (".json", ".csv"):
        out = tmp_path / f"{command}{suffix}"
        assert main([command, str(grid_3x3), "--out", str(out), "--quiet"]) == 0
        assert out.stat().st_size > 100
    text = capsys.readouterr().out
    assert {"register": "shift du (px):", "mae": "MAE vs the centre PSF",
            "warp": "residual displacement rms"}[command] in text


def _saturated_grid(path):
    v, u = np.mgrid[0:64, 0:80]
    with GridWriter(path, (1, 3), black_level=100, bit_depth=12) as w:
        for c in range(3):
            spot = 9000.0 * np.exp(-((v - 30) ** 2 + (u - 30 - 5 * c) ** 2) / 18.0)
            w.add(0, c, np.clip(spot + 100, 0, 4095).astype(np.uint16)[None],
                  field_deg=(c - 1.0, 0.0))


@pytest.mark.parametrize("argv,message", [
    (["report", "{tmp}/nogrid", "--out", "{tmp}/rep"], "nogrid: no such grid folder"),
    (["register", "{grid}", "--out", "{tmp}/shifts.txt"], "must end in .json or .csv"),
    (["report", "{sat}", "--out", "{tmp}/rep"], "psf_r00_c01.tiff: "),
])
def test_bad_input_one_line_no_output(grid_3x3, tmp_path, capsys, argv, message):
    _saturated_grid(tmp_path / "sat")
    argv = [a.format(tmp=tmp_path, grid=grid_3x3, sat=tmp_path / "sat") for a in argv]
    assert main([*argv, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "rep").exists() and not (tmp_path / "shifts.txt").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_saturated_grid_passes_with_allow_saturated(tmp_path, capsys):
    _saturated_grid(tmp_path / "sat")
    assert main(["register", str(tmp_path / "sat"), "--allow-saturated", "--quiet"]) == 0
    assert "saturated pixels" in capsys.readouterr().out


def test_per_channel_prints_each_channels_shifts(grid_3x3, capsys):
    """Without --out, --per-channel still acts: one shift grid per channel and axis."""
    assert main(["register", str(grid_3x3), "--quiet"]) == 0
    plain = capsys.readouterr().out
    assert main(["register", str(grid_3x3), "--per-channel", "--quiet"]) == 0
    per_channel = capsys.readouterr().out
    assert per_channel.startswith(plain.split("registration quality")[0])
    for c in range(3):
        for axis in ("du", "dv"):
            assert f"channel {c} shift {axis} (px):" in per_channel
    assert "channel 0 shift" not in plain
