"""Issue 26 from the command line: a grid with missing corners and bad captures gives a full
report naming what it left out and why; --strict, --reference; an irregular scan."""

from __future__ import annotations

import json

import numpy as np
import pytest

from psfkit.cli import main
from psfkit.simulate import BenchConfig, simulate_grid, simulate_scan
from tests.helpers.degrade import degrade_grid


@pytest.fixture(scope="module")
def grids(tmp_path_factory):
    root = tmp_path_factory.mktemp("captures")
    full = simulate_grid(root / "full", BenchConfig(downsample=8), grid_shape=(5, 5),
                         progress=False)
    corners = [(0, 0), (0, 4), (4, 0), (4, 4)]
    bad = degrade_grid(full, root / "bad", drop=corners, saturate=[(1, 3)], empty=[(3, 1)])
    bad_centre = degrade_grid(full, root / "bad_centre", empty=[(2, 2)])
    rng = np.random.default_rng(3)
    fov_h, fov_w = BenchConfig(downsample=8).fov_monitor_px
    points = np.column_stack([rng.uniform(-0.4, 0.4, 15) * fov_w,
                              rng.uniform(-0.4, 0.4, 15) * fov_h])
    scan = simulate_scan(root / "scan", np.vstack([[0.0, 0.0], points]),
                         BenchConfig(downsample=8), progress=False)
    return {"bad": bad, "bad_centre": bad_centre, "scan": scan}


def test_report_of_a_grid_with_gaps_and_bad_captures(grids, tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["report", str(grids["bad"]), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "(incomplete lattice)" in text
    assert "not captured: 4 position(s) of the 5x5 lattice: (0, 0), (0, 4), (4, 0), (4, 4)" \
        in text
    assert "(1, 3) psf_r01_c03.tiff: saturated" in text
    assert "(3, 1) psf_r03_c01.tiff: no signal" in text
    doc = json.loads((out / "results.json").read_text())
    assert doc["layout"] == "incomplete lattice" and doc["positions_measured"] == 19
    assert sorted(e["reason"] for e in doc["excluded"]) == ["no signal", "saturated"]
    html = (out / "report.html").read_text()
    assert "psf_r01_c03.tiff" in html[html.index("class='excluded'"):]
    assert html.count("data:image/png;base64,") == 5


def test_fit_eigen_on_a_grid_with_gaps_and_bad_captures(grids, tmp_path, capsys):
    kernels, figures = tmp_path / "k.npz", tmp_path / "fig"
    assert main(["fit-eigen", str(grids["bad"]), "--out", str(kernels), "--figures",
                 str(figures), "--folds", "4", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "to 19 PSFs of the 5x5 incomplete lattice" in text
    assert "psf_r01_c03.tiff: saturated" in text and "psf_r03_c01.tiff: no signal" in text
    fit = json.loads((figures / "fit.json").read_text())
    assert fit["positions_fitted"] == 19 and len(fit["excluded"]) == 2


@pytest.mark.parametrize("command", ["register", "fit-eigen"])
def test_strict_refuses_in_one_line(grids, tmp_path, capsys, command):
    argv = [command, str(grids["bad"]), "--strict", "--quiet"]
    if command == "fit-eigen":
        argv += ["--out", str(tmp_path / "k.npz")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    assert "grid index (0, 0), (0, 4), (4, 0), (4, 4) missing" in err
    assert not (tmp_path / "k.npz").exists()


def test_a_bad_centre_is_refused_and_another_reference_can_be_named(grids, capsys):
    assert main(["register", str(grids["bad_centre"]), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "psf_r02_c02.tiff: no point-source signal" in err
    assert "--reference" in err
    assert main(["register", str(grids["bad_centre"]), "--reference", "2,1", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "to the centre (2, 1)" in text and "(2, 2) psf_r02_c02.tiff: no signal" in text
    assert main(["register", str(grids["bad_centre"]), "--reference", "9,9", "--quiet"]) == 2
    assert "no captured position" in capsys.readouterr().err


def test_an_irregular_scan_from_info_to_kernels(grids, tmp_path, capsys):
    assert main(["info", str(grids["scan"]), "--quiet"]) == 0
    assert "layout:    irregular scan (16 positions" in capsys.readouterr().out
    out = tmp_path / "report"
    assert main(["report", str(grids["scan"]), "--out", str(out), "--quiet"]) == 0
    assert "(irregular)" in capsys.readouterr().out
    rows = (out / "positions.csv").read_text().splitlines()
    assert len(rows) == 17 and rows[1].startswith(",,psf_000.tiff")
    assert main(["fit-eigen", str(grids["scan"]), "--out", str(tmp_path / "k.npz"),
                 "--cv-bases", "none", "--quiet"]) == 0
    assert "16 PSFs of an irregular scan" in capsys.readouterr().out
    assert main(["info", str(grids["scan"]), "--strict", "--quiet"]) == 2
