"""Issue 43: every PSF saturated, with --allow-saturated: one line naming the reference, exit 2
(was ``invalid value (cannot reshape array of size 9 into shape (2)) ... this is a bug``)."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
import tifffile


@pytest.fixture(scope="module")
def saturated_grid(grid_3x3, tmp_path_factory):
    """The 3 × 3 bench grid with every PSF clipped at the sensor's top value everywhere."""
    out = tmp_path_factory.mktemp("saturated") / "grid"
    shutil.copytree(grid_3x3, out)
    for path in out.glob("psf_*.tiff"):
        image = tifffile.imread(path)
        tifffile.imwrite(path, np.full_like(image, np.iinfo(image.dtype).max))
    return out


@pytest.mark.parametrize("command", ["register", "fit-eigen"])
def test_cli_gives_one_line_not_a_bug(saturated_grid, tmp_path, command):
    extra = ["--out", str(tmp_path / "k.npz")] if command == "fit-eigen" else []
    run = subprocess.run([sys.executable, "-m", "psfkit.cli", command, str(saturated_grid),
                          "--allow-saturated", "--quiet", *extra],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, run.stderr
    assert "psf_r01_c01.tiff" in lines[0] and "saturated" in lines[0]
    assert "bug" not in lines[0] and "cannot reshape" not in lines[0]
    assert not (tmp_path / "k.npz").exists()


