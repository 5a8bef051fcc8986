"""The support box of a PSF and windows cut around it (what the figures show)."""

from __future__ import annotations

import numpy as np
import pytest

from psfkit.calibration.support import crop_window, support_box


def spot(shape: tuple[int, int], centre: tuple[float, float], sigma: float) -> np.ndarray:
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    return np.exp(-((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2) / (2 * sigma**2))


def test_a_compact_psf_on_a_large_noisy_frame_gets_a_small_box_around_it():
    rng = np.random.default_rng(0)
    image = spot((600, 800), (412.3, 95.7), 1.5) + rng.normal(0, 0.01, (600, 800))
    image[20, 700] = 5.0                         # a hot pixel far away: not the PSF
    rows, cols = support_box(image)
    assert rows.start < 412 < rows.stop and cols.start < 96 < cols.stop
    # the support (2 % of the peak: 2.8 σ each side) plus a margin of >= 3 px, not the frame
    assert 12 <= rows.stop - rows.start <= 24 and 12 <= cols.stop - cols.start <= 24


def test_a_caustic_filling_the_frame_keeps_its_extent():
    image = np.zeros((120, 160))
    image[30:90, 40:130] = 1.0
    rows, cols = support_box(image)
    assert rows.start <= 30 and rows.stop >= 90 and cols.start <= 40 and cols.stop >= 130
    assert rows.stop - rows.start <= 1.4 * 60 and cols.stop - cols.start <= 1.4 * 90


def test_a_large_frame_is_searched_binned_and_the_box_still_holds_the_psf():
    rng = np.random.default_rng(1)
    image = spot((3000, 4000), (2210.0, 333.0), 2.0) + rng.normal(0, 0.005, (3000, 4000))
    rows, cols = support_box(image)
    assert rows.start < 2210 - 5 and rows.stop > 2210 + 5
    assert cols.start < 333 - 5 and cols.stop > 333 + 5
    assert rows.stop - rows.start <= 40 and cols.stop - cols.start <= 40


def test_an_empty_frame_is_shown_whole():
    assert support_box(np.zeros((10, 20))) == (slice(0, 10), slice(0, 20))


@pytest.mark.parametrize("offset", [(0, 0), (7, -3), (-20, 40)])
def test_a_window_moved_by_the_shift_follows_the_psf_and_pads_off_the_frame(offset):
    base = spot((100, 120), (50, 60), 2.0)
    moved = spot((100, 120), (50 + offset[0], 60 + offset[1]), 2.0)
    box = support_box(base)
    window = crop_window(moved[None], box, offset)[0]
    reference = crop_window(base, box)
    inside = np.isfinite(window)
    np.testing.assert_allclose(window[inside], reference[inside], atol=1e-6)
    # pixels of the window beyond the frame are NaN ("off the sensor"), none are lost inside
    r0, c0 = box[0].start + offset[0], box[1].start + offset[1]
    rows, cols = np.mgrid[r0:r0 + window.shape[0], c0:c0 + window.shape[1]]
    on_frame = (rows >= 0) & (rows < 100) & (cols >= 0) & (cols < 120)
    np.testing.assert_array_equal(inside, on_frame)
