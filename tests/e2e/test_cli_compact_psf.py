"""Issue 43 from the command line: irregular scans of a compact PSF with 117 and 300 positions
(a field of stars) pass `psfkit info`, `report` and `register`, every position accepted and
reliable (small frames: the CLI path, not the numerics, is under test here)."""

from __future__ import annotations

import json

import pytest

from psfkit.cli import main
from research.compact_bench import CompactCamera, simulate_compact_scan


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    root = tmp_path_factory.mktemp("stars")
    return {117: simulate_compact_scan(root / "s117", 117, (64, 64),
                                       CompactCamera(edge_margin_px=8), seed=1),
            300: simulate_compact_scan(root / "s300", 300, (40, 40),
                                       CompactCamera(edge_margin_px=6), seed=2)}


@pytest.mark.parametrize("n", [117, 300])
def test_info_reads_a_scan_of_any_length(scans, n, capsys):
    assert main(["info", str(scans[n]), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert f"irregular scan ({n} positions" in text and "exceeds the limit" not in text


def test_report_of_117_stars(scans, tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["report", str(scans[117]), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    results = json.loads((out / "results.json").read_text())
    assert results["grid_shape"] == [1, 117] and len(results["positions"]) == 117
    assert results["excluded"] == [] and results["layout"] == "irregular"
    assert min(p["support_overlap"] for p in results["positions"]) > 0.99
    assert "less than 50% of the centre PSF's light" not in text
    assert (out / "report.html").is_file()
    # issue 43's target: a PSF that does not vary is judged so, from every position
    assert results["verdict"]["shift_variant"] is False
    assert results["verdict"]["recommended_model"] == "si"
    # the terminal summarises a long scan (each position is in positions.csv), and prints no
    # number without its uncertainty or judgement, and no nan
    assert "117 positions: min" in text and "#116" not in text
    assert len(text.splitlines()) < 40 and "nan" not in text.lower()


def test_register_300_stars(scans, tmp_path, capsys):
    out = tmp_path / "shifts.json"
    assert main(["register", str(scans[300]), "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    results = json.loads(out.read_text())
    assert len(results["positions"]) == 300 and results["excluded"] == []


def test_fit_eigen_auto_on_stars_writes_one_psf_and_explains_its_errors(scans, tmp_path,
                                                                        capsys):
    """`fit-eigen --basis auto` follows the verdict (one PSF for a PSF that does not vary),
    never contradicts it, and says that the errors it prints hold the stars' brightness
    ratios (10x here) unless --gain-compensate."""
    out = tmp_path / "k.npz"
    assert main(["fit-eigen", str(scans[117]), "--basis", "auto", "--out", str(out),
                 "--quiet"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("fitted basis 'si'") and "note:" not in text
    assert "light varies" in text and "--gain-compensate" in text
    assert main(["fit-eigen", str(scans[117]), "--basis", "auto", "--gain-compensate",
                 "--out", str(tmp_path / "g.npz"), "--quiet"]) == 0
    assert "light varies" not in capsys.readouterr().out
