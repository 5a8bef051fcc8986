"""Preprocessing: background, hot pixels, saturation, empty captures, exposure."""

import numpy as np
import pytest

from psfkit.calibration.preprocess import (
    GridCalibration,
    PreprocessOptions,
    hot_pixel_mask,
    prepare_psf,
    saturation_level_for,
)
from psfkit.characterization.characterize import characterize_grid
from psfkit.errors import GridFormatError, InvalidInputError
from psfkit.io import GridWriter, read_grid


def _spot(shape=(64, 80), center=(30, 40), peak=3000.0, width=3.0):
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    return peak * np.exp(-((v - center[0]) ** 2 + (u - center[1]) ** 2) / (2 * width**2))


def _raw(image, black=100.0, noise=2.0, seed=0):
    rng = np.random.default_rng(seed)
    return np.clip(np.rint(image + black + rng.normal(0, noise, image.shape)), 0,
                   4095).astype(np.uint16)[None]


def test_dark_frame_and_hot_pixels():
    dark = _raw(np.zeros((64, 80)), seed=1)
    dark[0, 10, 12] = 2500                         # a hot pixel
    mask = hot_pixel_mask(dark.astype(np.float32))
    assert mask[10, 12] and mask.sum() == 1
    raw = _raw(_spot(), seed=2)
    raw[0, 10, 12] = 2600
    prepared = prepare_psf(raw, dark=dark.astype(np.float32), hot_pixels=mask)
    assert abs(prepared.image[0, 10, 12]) < 20     # repaired from its neighbours
    assert prepared.image[0, 30, 40] == pytest.approx(3000, rel=0.01)
    assert abs(np.median(prepared.image)) < 2      # background removed


def test_saturation_is_refused_unless_allowed():
    raw = _raw(_spot(peak=9000.0), seed=3)       # clips at 4095 over a wide core
    with pytest.raises(InvalidInputError, match=r"psf\.tiff: .* saturated pixels") as info:
        prepare_psf(raw, black_level=100, saturation_level=4095, name="psf.tiff")
    assert "--allow-saturated" in str(info.value)
    prepared = prepare_psf(raw, black_level=100, saturation_level=4095,
                           options=PreprocessOptions(allow_saturated=True))
    assert prepared.n_saturated > 10
    assert prepared.saturated[30, 40] and not prepared.saturated[0, 0]


def test_empty_capture_is_refused():
    with pytest.raises(InvalidInputError, match=r"empty\.tiff: no point-source signal"):
        prepare_psf(_raw(np.zeros((64, 80))), black_level=100, name="empty.tiff")


def test_saturation_level_from_bit_depth(tmp_path):
    for stored_max, bit_depth, expected in [(4095, 12, 4095.0), (65520, 12, 65520.0)]:
        out = tmp_path / f"g{stored_max}"
        with GridWriter(out, (1, 1), bit_depth=bit_depth) as w:
            image = np.full((1, 12, 12), 10, np.uint16)   # the smallest PSF frame
            image[0, 6, 6] = stored_max
            w.add(0, 0, image)
        assert saturation_level_for(read_grid(out)) == expected


def test_exposures_are_normalised_to_the_centre(tmp_path):
    out = tmp_path / "exp"
    spot = _spot(peak=1500.0)
    with GridWriter(out, (1, 3), black_level=100) as w:
        for c, exposure in enumerate([0.02, 0.01, 0.02]):   # centre (c = 1) at 10 ms
            w.add(0, c, _raw(spot * exposure / 0.01, seed=c), exposure_s=exposure,
                  field_deg=(c - 1.0, 0.0))
    grid = read_grid(out)
    options = PreprocessOptions()
    calib = GridCalibration.from_grid(grid, options)
    centre = calib.prepare(grid, 0, 1, options).image
    double = calib.prepare(grid, 0, 0, options).image
    assert centre.max() == pytest.approx(1500, rel=0.02)
    assert double.max() == pytest.approx(centre.max(), rel=0.02)  # 2× light, 2× time


def test_grid_without_centre_is_refused(tmp_path):
    out = tmp_path / "even"
    with GridWriter(out, (2, 2), black_level=100) as w:
        for r in range(2):
            for c in range(2):
                w.add(r, c, _raw(_spot(), seed=r * 2 + c))
    with pytest.raises(GridFormatError, match="has no centre position"):
        characterize_grid(read_grid(out))
