"""Issue 43 from the command line: the verdict opens psfkit report (terminal, results.json,
HTML); fit-eigen --basis auto writes the model it recommends and prints no note that
contradicts it; every fitted field quantity is printed with its uncertainty, never ``nan``."""

from __future__ import annotations

import json
import re

from psfkit.cli import main
from psfkit.forward.kernelfile import load_kernels

NAN = re.compile(r"\bnan\b", re.IGNORECASE)


def test_report_opens_with_the_verdict(grid_5x5, tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["report", str(grid_5x5), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    assert lines[0].startswith("verdict: The PSF shape varies over the field beyond noise: "
                               "use the eigen-kernel model ")
    assert "noise floor (held-out error of si+sampling)" in text
    assert re.search(r"vignetting: gain = A cos\^n\(theta\), n = \d\.\d+ ± \d", text)
    assert re.search(r"magnification \d\.\d+ ± ", text)
    assert not NAN.search(text)
    doc = json.loads((out / "results.json").read_text())
    verdict = doc["verdict"]
    assert verdict["shift_variant"] is True and verdict["recommended_model"] != "si"
    assert set(verdict["effects"]) == {"shift", "gain", "warp", "astigmatism"}
    assert verdict["effects"]["gain"]["significant"] is True
    evidence = verdict["evidence"]
    assert evidence["positions"] == 24 and evidence["noise_floor"]["sigma"] > 0
    assert all(v["sigma"] > 0 for v in evidence["held_out"].values())
    assert doc["gain_fit"]["estimates"]["cos_exponent"]["significant"] is True
    assert "estimates" in doc["shift_map"] and "estimates" in doc["warp_growth"]
    page = (out / "report.html").read_text()
    assert page.index("class='verdict'") < page.index("<h2")
    assert "The PSF shape varies over the field beyond noise" in page
    assert "not detected" in page                      # e.g. the warp growth at 8× binning


def test_fit_eigen_auto_writes_one_psf_for_the_field_free_camera(grid_5x5_field_free,
                                                                  tmp_path, capsys):
    out = tmp_path / "k.npz"
    assert main(["fit-eigen", str(grid_5x5_field_free), "--basis", "auto", "--out", str(out),
                 "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "verdict: The PSF shape does not change over the field beyond noise" in text
    assert "note:" not in text and "rerun" not in text and not NAN.search(text)
    model = load_kernels(out)
    assert model.basis == "si" and len(model.kernels) == 1
    assert model.provenance["fit"]["verdict"]["recommended_model"] == "si"


def test_fit_eigen_auto_follows_the_verdict_and_a_fixed_basis_gets_one_note(grid_5x5,
                                                                            tmp_path, capsys):
    auto = tmp_path / "auto.npz"
    assert main(["fit-eigen", str(grid_5x5), "--basis", "auto", "--out", str(auto),
                 "--quiet"]) == 0
    text = capsys.readouterr().out
    model = load_kernels(auto)
    recommended = model.provenance["fit"]["verdict"]["recommended_model"]
    assert recommended == f"{model.basis}/{model.convention}" and model.basis != "si"
    assert f"use the eigen-kernel model {recommended}" in text
    assert "note:" not in text and not NAN.search(text)
    assert re.search(r"Kv − Kbase: \d\.\d+ ± \d", text)
    # the contradiction: a basis the verdict does not recommend, written on request,
    # gets one note that names the recommended model, and no advice about another convention
    si = tmp_path / "si.npz"
    assert main(["fit-eigen", str(grid_5x5), "--basis", "si", "--cv-bases", "all",
                 "--out", str(si), "--quiet"]) == 0
    text = capsys.readouterr().out
    notes = [line for line in text.splitlines() if "note:" in line]
    assert notes == [f"  note: the verdict recommends {recommended}, this file holds si; "
                     "rerun with --basis auto to write the recommended model"]
    assert "--convention" not in text and "best:" not in text


def test_register_and_warp_print_uncertainties_never_nan(grid_3x3, capsys):
    assert main(["register", str(grid_3x3), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert re.search(r"magnification \d\.\d+ ± \d", text)
    assert "distortion beyond the affine map not determined (9 positions are too few" in text
    assert main(["warp", str(grid_3x3), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "warp residual growth" in text and "tangential/sagittal ratio" in text
    assert not NAN.search(text)
