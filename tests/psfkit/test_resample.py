"""psfkit.numerics.resample: block sums and means, against hand-computed blocks."""

from __future__ import annotations

import numpy as np
import pytest

from psfkit.errors import InvalidInputError
from psfkit.numerics.resample import bin_image, bin_mean, binning_factor


def test_bin_image_sums_blocks_of_the_last_two_axes():
    image = np.arange(24.0).reshape(1, 4, 6)
    binned = bin_image(image, 2)
    assert binned.shape == (1, 2, 3)
    assert binned.sum() == image.sum()
    assert binned[0, 0, 0] == 0 + 1 + 6 + 7
    assert binned[0, 1, 2] == 16 + 17 + 22 + 23
    assert bin_image(image, 1) is image


def test_bin_image_drops_trailing_pixels_unless_exact():
    image = np.arange(35, dtype=np.float32).reshape(5, 7)
    binned = bin_image(image, 2)
    assert binned.shape == (2, 3) and binned.dtype == np.float32
    assert binned[1, 2] == 18 + 19 + 25 + 26        # rows 2-3, columns 4-5; row 4, col 6 dropped
    with pytest.raises(InvalidInputError, match="not a multiple of 2"):
        bin_image(image, 2, exact=True)
    with pytest.raises(InvalidInputError):
        bin_image(image, 0)


def test_bin_mean_averages_in_float64():
    rng = np.random.default_rng(0)
    image = rng.random((2, 3, 9, 12)).astype(np.float32)
    mean = bin_mean(image, 3)
    assert mean.shape == (2, 3, 3, 4) and mean.dtype == np.float64
    expected = image[0, 1, 3:6, 6:9].astype(np.float64).mean()
    assert mean[0, 1, 1, 2] == pytest.approx(expected, rel=1e-15)
    # the block mean in the input's precision is the block sum over factor²
    np.testing.assert_allclose(bin_image(image, 3) / 9, mean, rtol=1e-6)


def test_binning_factor():
    assert binning_factor((480, 640), 160) == 4
    assert binning_factor((480, 641), 160) == 5
    assert binning_factor((100, 80), 160) == 1


def test_bin_image_sums_in_the_requested_precision():
    rng = np.random.default_rng(3)
    image = rng.random((2, 31, 45)).astype(np.float32) * 1e3
    sums = bin_image(image, 3, dtype=np.float64)
    assert sums.dtype == np.float64
    # float64 sums of the float32 values: exactly those of a float64 copy
    assert np.array_equal(sums, bin_image(image.astype(np.float64), 3))
    assert bin_image(image, 1, dtype=np.float64).dtype == np.float64
