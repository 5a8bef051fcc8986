"""The compact-PSF bench (issue 43): an irregular scan of a few-pixel Airy PSF on a large
frame, its ground truth, and the same scan as pre-centred cut-outs."""

from __future__ import annotations

import numpy as np
import pytest

from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.io import read_grid
from research.compact_bench import (
    CompactCamera,
    cutout_scan,
    read_compact_truth,
    simulate_compact_scan,
)
from research.compact_bench.airy import AIRY_HALF_MAX_X, airy_stamp


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    return simulate_compact_scan(tmp_path_factory.mktemp("compact") / "scan", 40, (160, 200),
                                 seed=3)


def test_airy_stamp_has_its_fwhm_centre_and_unit_sum():
    stamp = airy_stamp(61, (30.3, 29.6), 6.0)
    assert stamp.sum() == pytest.approx(1.0)
    ys, xs = np.mgrid[:61, :61]
    assert (stamp * xs).sum() == pytest.approx(30.3, abs=0.01)     # centroid = centre
    assert (stamp * ys).sum() == pytest.approx(29.6, abs=0.01)
    # the half-maximum contour of a finely sampled, centred profile sits at FWHM / 2
    fine = airy_stamp(241, (120.0, 120.0), 24.0)
    row = fine[120] / fine[120].max()
    above = np.flatnonzero(row >= 0.5)
    assert above[-1] - above[0] + 1 == pytest.approx(24.0, abs=1.5)
    assert AIRY_HALF_MAX_X == pytest.approx(1.6163, abs=1e-4)
    # elongated along 45°: wider along the diagonal than across it
    long = airy_stamp(61, (30.0, 30.0), 4.0, axis_ratio=2.0, orientation_rad=np.pi / 4)
    assert long[35, 35] > 3 * long[25, 35]


def test_scan_is_an_irregular_grid_with_its_truth(scan):
    grid = read_grid(scan)
    truth = read_compact_truth(scan)
    assert grid.layout == "irregular" and grid.grid_shape == (1, 40)
    assert grid.center_index == (0, 0) and grid.image_shape == (1, 160, 200)
    assert np.allclose(grid.field_deg()[0], truth.field_deg, atol=1e-8)
    # the reference is on the axis; shifts are positions relative to it
    assert np.allclose(truth.shift_px, truth.position_px - truth.position_px[0])
    assert np.allclose(truth.shift_px[0], 0.0)
    # the true map: shift = A · tan θ (no distortion by default), an inverted, rotated image
    tan = np.tan(np.deg2rad(truth.field_deg))
    matrix = np.array(truth.info["shift_matrix_px_per_tan"])
    assert np.allclose(tan @ matrix.T, truth.shift_px, atol=1e-6)
    assert np.linalg.det(matrix) > 0 and matrix[0, 0] < 0        # rotation by ~180°
    # the brightest source is the reference; brightness spans the range asked for
    assert truth.flux_e.argmax() == 0 and truth.flux_e.max() / truth.flux_e.min() <= 10.0
    # a field-independent PSF by default
    assert np.allclose(truth.fwhm_px, 3.0) and np.allclose(truth.axis_ratio, 1.0)


def test_frames_hold_the_sources_with_poisson_gaussian_noise(scan):
    grid = read_grid(scan)
    truth = read_compact_truth(scan)
    sensor = truth.camera.sensor
    for p in (0, 7, 23):
        frame = grid.load(0, p)[0].astype(np.float64) - grid.black_level
        x, y = truth.position_px[p]
        peak = np.unravel_index(np.argmax(frame), frame.shape)
        assert abs(peak[0] - y) <= 1 and abs(peak[1] - x) <= 1
        # the background is read noise (in stored units: 16 per ADC unit)
        background = frame[:20, :20] / sensor.container_scale
        expected = sensor.read_noise_e / sensor.electrons_per_dn
        assert np.std(background) == pytest.approx(np.hypot(expected, 1 / np.sqrt(12)),
                                                   rel=0.3)
        # the signal above background is the flux (in electrons) times the stamp's share
        left, top = truth.info["positions"][p]["stamp_corner_px"]
        size = truth.stamps.shape[-1]
        rows = slice(max(top, 0), min(top + size, 160))
        cols = slice(max(left, 0), min(left + size, 200))
        inside = truth.stamps[p][rows.start - top:rows.stop - top,
                                 cols.start - left:cols.stop - left].sum()
        total = frame[rows, cols].sum() / sensor.container_scale * sensor.electrons_per_dn
        assert total == pytest.approx(truth.flux_e[p] * inside, rel=0.06)


def test_field_variation_grows_with_radius(tmp_path):
    folder = simulate_compact_scan(tmp_path / "v", 12, (128, 128),
                                   CompactCamera(width_growth=1.0, ellipticity=0.5,
                                                 edge_margin_px=10))
    truth = read_compact_truth(folder)
    radius = np.hypot(*truth.shift_px.T)
    order = np.argsort(radius)
    assert np.all(np.diff(truth.fwhm_px[order]) >= -1e-12)
    assert truth.fwhm_px[0] == 3.0 and truth.fwhm_px.max() > 3.5
    assert truth.axis_ratio.max() > 1.2 and truth.stamps.shape[0] == 12


def test_cutouts_hold_the_same_pixels_and_truth(scan, tmp_path):
    cut = cutout_scan(scan, tmp_path / "cut", 31)
    full, crops = read_grid(scan), read_grid(cut)
    truth, local = read_compact_truth(scan), read_compact_truth(cut)
    assert crops.grid_shape == (1, 40) and crops.image_shape == (1, 31, 31)
    assert crops.center_index == (0, 0)
    for p in (0, 5, 39):
        left, top = local.info["positions"][p]["crop_corner_px"]
        assert np.array_equal(crops.load(0, p)[0],
                              full.load(0, p)[0, top:top + 31, left:left + 31])
        # pre-centred: the source within half a pixel of the middle (unless clamped)
        assert np.allclose(local.position_px[p], truth.position_px[p] - [left, top])
    assert np.all(np.abs(local.position_px - 15) <= 0.5 + 1e-9)
    assert np.allclose(local.shift_px, local.position_px - local.position_px[0])
    assert local.info["crop"]["size"] == 31 and local.frame_shape == (31, 31)


def test_bad_requests_are_refused(tmp_path, scan):
    with pytest.raises(ConfigurationError, match="n_positions"):
        simulate_compact_scan(tmp_path / "a", 2, (64, 64))
    with pytest.raises(ConfigurationError, match="too small"):
        simulate_compact_scan(tmp_path / "b", 5, (40, 40))
    with pytest.raises(ConfigurationError, match="fwhm_px"):
        CompactCamera(fwhm_px=0.1)
    with pytest.raises(ConfigurationError, match="cut-out size"):
        cutout_scan(scan, tmp_path / "c", 500)
    with pytest.raises(InvalidInputError, match="not a simulated scan"):
        read_compact_truth(tmp_path)
