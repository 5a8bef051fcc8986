"""The whole pipeline on a real caustic with known transforms (issue 3 real-data targets).

A 3 × 3 grid is built from the measured DiffuserCam PSF: each position is the PSF displaced
by a known sub-pixel shift, scaled by a known gain and, on the diagonals, warped by a known
small affine map, with noise and a dark level, stored as 16-bit TIFF (the transforms are
applied with scipy splines, independently of psfkit's own Fourier shifts).
"""

import numpy as np
import pytest
from scipy import ndimage

from psfkit.characterization.characterize import characterize_grid
from psfkit.io import GridWriter, read_grid
from psfkit.numerics.resample import bin_image

BLACK = 200


def _transform(image, matrix, shift, gain):
    """``moving(x + D(x)) = gain · image(x)``, ``D(x) = (M − I)(x − c) + s``, x = (u, v)."""
    h, w = image.shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    target = np.stack([u.ravel() - c[0] - shift[0], v.ravel() - c[1] - shift[1]])
    source = np.linalg.solve(matrix, target) + c[:, None]
    moved = ndimage.map_coordinates(image, [source[1], source[0]], order=5, mode="constant")
    d = np.einsum("ij,jhw->ihw", matrix - np.eye(2), np.stack([u - c[0], v - c[1]]))
    return gain * moved.reshape(h, w), d + np.asarray(shift)[:, None, None]


@pytest.fixture(scope="module")
def real_grid(real_caustic, tmp_path_factory):
    psf = bin_image(np.clip(real_caustic, 0, None), 2)          # 600 × 800
    psf *= 20000.0 / psf.max()
    rng = np.random.default_rng(7)
    truth = {}
    out = tmp_path_factory.mktemp("real") / "grid"
    with GridWriter(out, (3, 3), black_level=BLACK) as writer:
        for r in range(3):
            for c in range(3):
                i, j = c - 1, r - 1
                shift = (-60.0 * i + 0.37 * i + 0.11 * j, -45.0 * j + 0.23 * j - 0.07 * i)
                gain = 1.0 - 0.03 * (i * i + j * j)
                diagonal = i != 0 and j != 0
                eps = np.array([[0.004, 0.002], [-0.001, -0.003]]) if diagonal else 0.0
                matrix = np.eye(2) + eps
                image, displacement = _transform(psf, matrix, shift, gain)
                raw = rng.poisson(np.clip(image, 0, None)) + rng.normal(BLACK, 3.0, image.shape)
                writer.add(r, c, np.clip(np.rint(raw), 0, 65535).astype(np.uint16)[None],
                           monitor_px=(100.0 * i, 100.0 * j))
                truth[(r, c)] = {"shift": shift, "gain": gain, "affine": diagonal,
                                 "displacement": displacement}
    return out, truth


@pytest.fixture(scope="module")
def characterized(real_grid):
    path, truth = real_grid
    return characterize_grid(read_grid(path)), truth


def test_shifts_within_005_px(characterized):
    result, truth = characterized
    for p in result.positions:
        t = truth[(p.row, p.col)]
        if not t["affine"]:
            assert p.shift == pytest.approx(t["shift"], abs=0.05)


def test_gains_within_1_percent(characterized):
    result, truth = characterized
    for p in result.positions:
        t = truth[(p.row, p.col)]
        if not t["affine"]:
            assert p.gain == pytest.approx(t["gain"], rel=0.01)


def test_warp_median_endpoint_error_below_01_px(characterized, real_grid):
    """Total displacement (registration + warp) against the known affine maps."""
    from psfkit.calibration.preprocess import GridCalibration, PreprocessOptions
    from psfkit.calibration.registration import shift_image
    from psfkit.calibration.warp import warp_field

    result, truth = characterized
    path, _ = real_grid
    grid = read_grid(path)
    options = PreprocessOptions()
    calib = GridCalibration.from_grid(grid, options)
    reference = calib.prepare(grid, 1, 1, options).luminance
    checked = 0
    for p in result.positions:
        t = truth[(p.row, p.col)]
        if not t["affine"]:
            continue
        aligned, valid = shift_image(calib.prepare(grid, p.row, p.col, options).luminance,
                                     p.shift)
        warp = warp_field(reference, aligned / p.gain, valid)
        total = warp.displacement() + np.asarray(p.shift)[:, None, None]
        error = np.hypot(*(total - t["displacement"]))[warp.mask]
        assert np.median(error) <= 0.1
        assert warp.affine.scale_u == pytest.approx(1.004, abs=5e-4)
        assert warp.affine.scale_v == pytest.approx(0.997, abs=5e-4)
        checked += 1
    assert checked == 4


def test_shift_map_of_the_synthetic_grid(characterized):
    result, _ = characterized
    fit = result.shift_fit
    assert fit.field_units == "monitor px"
    # 60 px per 100 monitor px along u, 45 per 100 along v, inverted
    np.testing.assert_allclose(np.diag(fit.matrix), [-0.5963, -0.4477], atol=2e-3)
