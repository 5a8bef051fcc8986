"""The analysis/ scripts, each run as a command on a small simulated grid."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from psfkit.bench import BenchConfig, simulate_grid
from psfkit.grid_fit import EigenFitOptions, fit_eigen_grid
from psfkit.io import read_grid
from psfkit.kernelfile import KernelModel, save_kernels

ANALYSIS = Path(__file__).resolve().parents[1] / "analysis"


def _run(script: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ANALYSIS / script), *args], capture_output=True,
                          text=True, timeout=300, check=False)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("analysis")
    grid = simulate_grid(root / "grid", BenchConfig(downsample=8), grid_shape=(3, 3),
                         extent=0.8, progress=False)
    model = fit_eigen_grid(read_grid(grid), EigenFitOptions(cv_bases=())).kernel_model()
    learned, initial = root / "learned.npz", root / "initial.npz"
    save_kernels(learned, model)
    save_kernels(initial, KernelModel(kernels=np.stack([model.kernels[0]] * 3),
                                      sensor_shape=model.sensor_shape))
    return grid, learned, initial


def _nontrivial(path: Path, size: int = 10_000) -> None:
    assert path.is_file() and path.stat().st_size > size, path


def test_fig2(bench, tmp_path):
    grid, _, _ = bench
    done = _run("fig2_shift_variance.py", str(grid), "--out", str(tmp_path / "f2"), "--quiet")
    assert done.returncode == 0, done.stderr
    for ext in ("png", "pdf"):
        _nontrivial(tmp_path / "f2" / f"fig2_shift_variance.{ext}")
    doc = json.loads((tmp_path / "f2" / "fig2.json").read_text())
    maes = [r["mae"] for r in doc["centre_column"]]
    assert len(maes) == 3 and min(maes) == 0.0 and max(maes) > 0


def test_fig3(bench, tmp_path):
    _, learned, _ = bench
    done = _run("fig3_weight_maps.py", "--kernels", str(learned), "--out", str(tmp_path / "f3"))
    assert done.returncode == 0, done.stderr
    _nontrivial(tmp_path / "f3" / "fig3_weight_maps.png")
    doc = json.loads((tmp_path / "f3" / "fig3.json").read_text())
    assert doc["sensor_shape"] == [135, 180]
    assert doc["ranges"]["v"][1] == pytest.approx(0.5, abs=0.01)
    done = _run("fig3_weight_maps.py", "--sensor", "64", "96", "--out", str(tmp_path / "f3b"))
    assert done.returncode == 0, done.stderr


def test_fig7(bench, tmp_path):
    grid, learned, initial = bench
    out = tmp_path / "f7"
    done = _run("fig7_learned_kernels.py", str(learned), str(grid), "--initial", str(initial),
                "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    assert "learned: v_vs_kernels 1.000" in done.stdout
    for stem in ("fig7", "fig7_zoom", "fig7_learned_vs_measured", "displacements"):
        _nontrivial(out / "figures" / f"{stem}.png")
        _nontrivial(out / "figures" / f"{stem}.pdf")
    assert json.loads((out / "compare.json").read_text())["initial"] is not None


def test_scripts_fail_in_one_line(bench, tmp_path):
    grid, _, _ = bench
    done = _run("fig7_learned_kernels.py", str(tmp_path / "absent.npz"), str(grid),
                "--out", str(tmp_path / "x"))
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "no such kernel file" in done.stderr
    assert not (tmp_path / "x").exists()
