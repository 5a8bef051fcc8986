"""The psfkit command line: works first time, fails with one clear line."""

import json
import subprocess
import sys

import numpy as np
import pytest

from psfkit.cli import main


def test_simulate_grid_then_info(tmp_path, capsys):
    out = tmp_path / "grid"
    assert main(["simulate-grid", "--out", str(out), "--downsample", "8", "--rows", "3",
                 "--cols", "5", "--seed", "2", "--quiet"]) == 0
    assert main(["info", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "positions: 3 x 5 (15 images" in text
    assert "135 x 180 x 3 (R/G/B), uint16, 12-bit data" in text
    assert "centre:    (1, 2)" in text
    truth = json.loads((out / "ground_truth" / "truth.json").read_text())
    assert truth["config"]["seed"] == 2


def test_simulate_grid_mono_npy_with_bench_config(tmp_path, capsys):
    cfg = tmp_path / "bench.json"
    cfg.write_text(json.dumps({"diffusion_angle_deg": 0.5, "downsample": 8}))
    out = tmp_path / "grid"
    assert main(["simulate-grid", "--out", str(out), "--bench-config", str(cfg), "--mono",
                 "--format", "npy", "--rows", "1", "--cols", "3", "--no-dark", "--quiet"]) == 0
    assert sorted(p.name for p in out.glob("*.npy")) == [
        "psf_r00_c00.npy", "psf_r00_c01.npy", "psf_r00_c02.npy"]
    truth = json.loads((out / "ground_truth" / "truth.json").read_text())
    assert truth["config"]["diffusion_angle_deg"] == 0.5
    assert truth["channels"] == ["L"]


def test_simulate_grid_averaged_frames_then_info(tmp_path, capsys):
    """``--frames 4``: float32 means that ``info`` reads as a grid, N recorded in both files."""
    out = tmp_path / "grid"
    assert main(["simulate-grid", "--out", str(out), "--downsample", "16", "--rows", "1",
                 "--cols", "3", "--format", "npy", "--frames", "4", "--quiet"]) == 0
    assert main(["info", str(out), "--quiet"]) == 0
    assert "float32" in capsys.readouterr().out
    assert json.loads((out / "manifest.json").read_text())["simulation"]["frames_averaged"] == 4
    assert json.loads((out / "ground_truth" / "truth.json").read_text())["frames_averaged"] == 4


@pytest.mark.parametrize("argv,message", [
    (["info", "{tmp}/missing"], "missing: no such grid folder"),
    (["simulate-grid", "--out", "{tmp}/g", "--downsample", "0", "--quiet"],
     "argument --downsample: must be an integer in [1, 64]"),
    (["simulate-grid", "--out", "{tmp}/g", "--bench-config", "{tmp}/nope.json"],
     "nope.json: no such file"),
    (["simulate-grid", "--out", "{tmp}/g", "--rows", "0", "--quiet"],
     "argument --rows: must be an integer in [1, 64]"),
    (["simulate-grid", "--out", "{tmp}/g", "--frames", "0", "--quiet"],
     "argument --frames: must be an integer in [1, 10000]"),
    (["simulate-grid", "--out", "{tmp}/g", "--frames", "2", "--format", "png", "--quiet"],
     "write it as TIFF or .npy, not PNG"),
])
def test_errors_are_one_line_with_nonzero_exit(tmp_path, capsys, argv, message):
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("psfkit: error: ")
    assert message in err[0]
    assert not (tmp_path / "g").exists()


def test_console_script_reports_bad_grid_without_traceback(tmp_path):
    bad = tmp_path / "grid"
    bad.mkdir()
    (bad / "manifest.json").write_text("{not json")
    result = subprocess.run([sys.executable, "-m", "psfkit.cli.main", "info", str(bad)],
                            capture_output=True, text=True)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert result.stderr.strip().endswith("manifest.json: invalid JSON at line 1: "
                                          "Expecting property name enclosed in double quotes")


@pytest.mark.slow
def test_demo_measures_the_bench_ground_truth(tmp_path, capsys):
    """The main job as the README runs it (the default binning), checked against the virtual
    bench's ground truth, not only for files: at most 50 MB written, every field effect of the
    bench found, and the compact ground truth gives the clean PSFs the captures scatter about.
    (The demo's numbers at 8x binning are the golden test's.)"""
    from psfkit.forward.kernelfile import load_kernels
    from psfkit.io import read_grid
    from psfkit.simulate import read_ground_truth

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "virtual bench: 9 x 9 PSFs of 270 x 360 x 3" in text
    written = {p.relative_to(out).as_posix(): p.stat().st_size for p in out.rglob("*")
               if p.is_file()}
    assert sum(written.values()) <= 50e6                    # measured 25.5 MB
    assert max(written.values()) <= 5e6      # the kernels, 3.5 MB (psfs_clean.npy was 378 MB)
    assert "grid/ground_truth/truth.json" in written
    assert not any(name.endswith("psfs_clean.npy") for name in written)

    truth = read_ground_truth(out / "grid")
    results = json.loads((out / "report" / "results.json").read_text())
    rows, cols = truth.shift_px.shape[:2]
    by_index = {(p["row"], p["col"]): p for p in results["positions"]}
    shift = np.array([[by_index[r, c]["shift_px"] for c in range(cols)] for r in range(rows)])
    overlap = np.array([[by_index[r, c]["overlap"] for c in range(cols)] for r in range(rows)])
    gain = np.array([[by_index[r, c]["gain"] for c in range(cols)] for r in range(rows)])
    reliable = overlap >= results["reliable_overlap"]
    error = np.hypot(*np.moveaxis(shift - truth.shift_px, -1, 0))
    assert reliable.sum() >= 25
    assert np.sqrt(np.mean(error[reliable] ** 2)) < 0.1           # px rms (measured 0.027)
    assert np.abs(gain[reliable] / truth.gain[reliable] - 1).max() < 0.01
    assert results["gain_fit"]["cos_exponent"] == pytest.approx(4, abs=0.1)
    assert results["shift_map"]["magnification"] == pytest.approx(
        truth.info["magnification_px_per_monitor_px"], rel=1e-3)
    # why this binning: every field effect of the bench is significant (at 6x the
    # astigmatism is not), the warp growth with the oblique-incidence exponent p = 2
    effects = results["verdict"]["effects"]
    assert {name for name, e in effects.items() if e["significant"]} == {
        "shift", "gain", "warp", "astigmatism"}
    assert results["warp_growth"]["exponent"] == pytest.approx(
        2, abs=3 * results["warp_growth"]["exponent_std"])

    # the clean PSFs, computed again from the recorded bench, are what the (losslessly
    # compressed) captures scatter about
    grid = read_grid(out / "grid")
    for r, c in [(rows // 2, cols // 2), (0, cols - 1)]:
        signal = grid.load(r, c) - grid.black_level
        clean = truth.clean_psfs[r, c]
        bright = clean > 0.2 * clean.max()
        assert np.mean(signal[bright]) == pytest.approx(np.mean(clean[bright]), rel=0.02)
        assert np.corrcoef(signal.ravel(), clean.ravel())[0, 1] > 0.97

    kernels = load_kernels(out / "kernels.npz")
    assert kernels.basis == "paper" and kernels.sensor_shape == (270, 360)
    centre = truth.clean_psfs[rows // 2, cols // 2]
    base = kernels.kernels[0]
    ncc = np.sum((base - base.mean()) * (centre - centre.mean())) / (
        np.linalg.norm(base - base.mean()) * np.linalg.norm(centre - centre.mean()))
    assert ncc > 0.9                   # Kbase is the on-axis caustic of the bench
    held_out = kernels.provenance["fit"]["cross_validation"]["held_out_relative_error"]
    assert held_out["paper/sensor"] < 0.8 * held_out["centre PSF only"]
    assert (out / "kernels-figures" / "fig7_kernels.png").is_file()
    assert main(["demo", "--out", str(out), "--quiet"]) == 2
    assert "not empty" in capsys.readouterr().err


@pytest.mark.parametrize("script", ["psfkit", "ekdun"])
def test_console_scripts_are_installed(script):
    from pathlib import Path

    exe = Path(sys.executable).parent / script
    result = subprocess.run([str(exe), "--version"], capture_output=True, text=True)
    assert result.returncode == 0
    assert result.stdout.startswith(f"{script} 0.")


def _child_output(code: str, *args: str) -> str:
    """Last line printed by ``code`` run in a fresh interpreter (its own ``sys.modules``)."""
    result = subprocess.run([sys.executable, "-c", code, *args], capture_output=True,
                            text=True, check=True)
    return result.stdout.strip().splitlines()[-1]


def test_building_the_parser_imports_neither_torch_nor_ekdun():
    # psfkit --help and psfkit info must not pay for torch (seconds) nor reach into ekdun
    # (psfkit never imports ekdun); the commands import their heavy modules when they run.
    assert _child_output(
        "import sys; from psfkit.cli import main; from psfkit.cli.main import build_parser; "
        "build_parser(); print(sorted({m.split('.')[0] for m in sys.modules} "
        "& {'torch', 'ekdun', 'matplotlib', 'scipy', 'cv2'}))") == "[]"


def test_the_characterization_modules_do_not_import_scipy_signal():
    # scipy.signal (with scipy.stats and scipy.interpolate) costs ~0.4 s of start-up per
    # command, for one window function (psfkit.numerics.windows)
    assert _child_output(
        "import sys, psfkit.fitting.grid.fit, psfkit.characterization.characterize, "
        "psfkit.cli.fit_cmd; "
        "print(sorted(m for m in sys.modules if m.startswith(('scipy.signal', "
        "'scipy.stats'))))") == "[]"


def test_info_on_a_grid_imports_neither_torch_nor_ekdun(grid_3x3):
    assert _child_output(
        "import sys; from psfkit.cli import main; code = main(['info', sys.argv[1]]); "
        "print(code, sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'ekdun'}))",
        str(grid_3x3)) == "0 []"
