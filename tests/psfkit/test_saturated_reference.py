"""Issue 43: a grid whose every PSF is saturated, analysed with --allow-saturated.

Masking the saturated pixels of such a reference leaves nothing to compare with: every
position (the reference itself included) was excluded for "no overlap", and the shift-map fit
then failed with ``cannot reshape array of size 9 into shape (2)`` ("this is a bug"). The
reference is now refused with one line naming it, as any other unusable reference is.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import tifffile

from psfkit.calibration.preprocess import PreprocessOptions
from psfkit.characterization.characterize import CharacterizeOptions, characterize_grid
from psfkit.errors import InvalidInputError
from psfkit.io import read_grid


def saturate_every_psf(grid, out):
    """A copy of a bench grid with every PSF clipped at the sensor's top value everywhere."""
    shutil.copytree(grid, out)
    for path in out.glob("psf_*.tiff"):
        image = tifffile.imread(path)
        tifffile.imwrite(path, np.full_like(image, np.iinfo(image.dtype).max))
    return out


@pytest.fixture(scope="module")
def saturated_grid(grid_3x3, tmp_path_factory):
    return saturate_every_psf(grid_3x3, tmp_path_factory.mktemp("saturated") / "grid")


def test_fully_saturated_reference_is_refused_naming_it(saturated_grid):
    options = CharacterizeOptions(preprocess=PreprocessOptions(allow_saturated=True),
                                  steps=("register",))
    with pytest.raises(InvalidInputError, match=r"psf_r01_c01\.tiff.*saturated.*reference"):
        characterize_grid(read_grid(saturated_grid), options)


def test_table_of_a_grid_without_measured_positions_keeps_its_shape(grid_3x3):
    """The lattice of a vector quantity keeps its trailing axis when nothing was measured
    (the shape the fits read), instead of collapsing to ``(N, M)``."""
    result = characterize_grid(read_grid(grid_3x3), CharacterizeOptions(steps=("register",)))
    result.positions = []
    assert result.table("shift").shape == (3, 3, 2)
    assert np.isnan(result.table("shift")).all()
    assert result.table("gain").shape == (3, 3)
