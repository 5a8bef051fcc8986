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
    """``--out`` holds the numbers the command computed: JSON and CSV agree position by
    position, and the registered shifts are the bench's true ones (0.05 px rms is the
    registration's measured accuracy where most of a PSF is seen; 0.5 px at the corners, where
    only part of it is)."""
    from psfkit.simulate import read_ground_truth

    docs = {}
    for suffix in (".json", ".csv"):
        out = tmp_path / f"{command}{suffix}"
        assert main([command, str(grid_3x3), "--out", str(out), "--quiet"]) == 0
        docs[suffix] = out
    text = capsys.readouterr().out
    assert {"register": "shift du (px):", "mae": "MAE vs the centre PSF",
            "warp": "residual displacement rms"}[command] in text
    positions = json.loads(docs[".json"].read_text())["positions"]
    with open(docs[".csv"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(positions) == len(rows) == 9
    truth = read_ground_truth(grid_3x3)
    for pos, row in zip(positions, rows, strict=True):
        assert (int(row["row"]), int(row["col"])) == (pos["row"], pos["col"])
        du, dv = pos["shift_px"]
        assert float(row["shift_du_px"]) == pytest.approx(du, abs=1e-6)
        assert float(row["shift_dv_px"]) == pytest.approx(dv, abs=1e-6)
        true_du, true_dv = truth.shift_px[pos["row"], pos["col"]]
        limit = 0.15 if pos["overlap"] >= 0.5 else 0.5
        assert np.hypot(du - true_du, dv - true_dv) < limit, (pos["row"], pos["col"])
        if command == "mae" and (pos["row"], pos["col"]) != (1, 1):
            assert float(row["mae"]) == pytest.approx(pos["mae"], rel=1e-6) and pos["mae"] > 0
        if command == "warp" and (pos["row"], pos["col"]) != (1, 1):
            rms = pos["warp"]["residual_rms"]
            assert float(row["warp_residual_rms_px"]) == pytest.approx(rms, rel=1e-6)
            assert 0 < rms < 1


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
