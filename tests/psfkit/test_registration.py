"""Sub-pixel registration and the field → shift map, against known transforms."""

import numpy as np
import pytest
from scipy import ndimage

from psfkit.calibration.registration import (
    high_frequency_fraction,
    register_shift,
    shift_image,
)
from psfkit.calibration.shift_map import fit_shift_map
from psfkit.errors import InvalidInputError


@pytest.fixture(scope="module")
def caustic(real_caustic):
    """The real DiffuserCam PSF (1200 × 1600), dark level removed."""
    return real_caustic


def _moved(image, du, dv, pad=400):
    """``image`` displaced by (du, dv), made independently of psfkit (scipy Fourier shift on
    a zero-padded copy)."""
    spec = np.fft.fft2(np.pad(image, pad))
    return np.real(np.fft.ifft2(ndimage.fourier_shift(spec, (dv, du))))[pad:-pad, pad:-pad]


@pytest.mark.parametrize("shift", [(3.37, -2.81), (0.5, 0.5), (-0.03, 0.04),
                                   (-150.2, 40.6), (250.73, -180.27)])
def test_shifts_of_a_real_caustic_within_005_px(caustic, shift):
    rng = np.random.default_rng(0)
    noise = 0.002 * caustic.max()
    moving = _moved(caustic, *shift) + rng.normal(0, noise, caustic.shape)
    reference = caustic + rng.normal(0, noise, caustic.shape)
    du, dv = register_shift(reference, moving)
    assert du == pytest.approx(shift[0], abs=0.05)
    assert dv == pytest.approx(shift[1], abs=0.05)


def test_binned_refinement_is_refused_for_sharp_images():
    """White noise has most power above the binned Nyquist: registration must not bin it."""
    rng = np.random.default_rng(1)
    white = rng.random((1100, 1100))
    assert high_frequency_fraction(white) > 0.5
    moving = _moved(white, -7.7, 3.3, pad=50)
    du, dv = register_shift(white, moving)
    assert (du, dv) == pytest.approx((-7.7, 3.3), abs=0.02)


def test_shift_image_undoes_a_displacement(caustic):
    moving = _moved(caustic, 12.25, -7.5)
    aligned, valid = shift_image(moving, (12.25, -7.5))
    inner = valid & (np.abs(caustic) > 0)
    err = np.abs(aligned - caustic)[inner]
    assert err.max() < 1e-6 * caustic.max() * 1e3
    assert not valid[:, -13:].any() and not valid[:3].any()  # no data came from there
    assert valid[100:-100, 100:-100].all()


def test_shift_map_recovers_magnification_rotation_and_offset():
    ys, xs = np.mgrid[-4:5, -4:5] * 50.0
    positions = np.stack([xs, ys], axis=-1)
    m, rot = 2.3, np.deg2rad(180.0 + 0.8)           # an inverted, slightly rotated image
    matrix = m * np.array([[np.cos(rot), -np.sin(rot)], [np.sin(rot), np.cos(rot)]])
    offset = np.array([1.5, -0.75])
    shifts = positions @ matrix.T + offset
    fit = fit_shift_map(positions, shifts, "monitor px")
    assert fit.magnification == pytest.approx(m, rel=1e-9)
    assert fit.rotation_deg == pytest.approx(-179.2, abs=1e-6)
    np.testing.assert_allclose(fit.offset, offset, atol=1e-9)
    assert not fit.mirrored
    assert fit.rms_residual < 1e-9
    # a barrel-like distortion shows up in the residuals, not in the affine part
    r2 = np.sum(positions**2, axis=-1, keepdims=True)
    distorted = shifts + 1e-6 * r2 * positions
    fit = fit_shift_map(positions, distorted, "monitor px")
    assert fit.rms_residual > 0.1
    mirror = fit_shift_map(positions, positions * np.array([-1.0, 1.0]), "monitor px")
    assert mirror.mirrored


def test_shift_map_needs_a_two_dimensional_grid():
    positions = np.stack([np.arange(5.0), np.zeros(5)], axis=-1)[None]
    with pytest.raises(InvalidInputError, match="do not span two directions"):
        fit_shift_map(positions, positions, "grid steps")


def test_a_constant_background_does_not_pin_the_shift(caustic):
    moving = _moved(caustic, -180.4, 129.6) + 1000.0
    du, dv = register_shift(caustic + 1000.0, moving)
    assert (du, dv) == pytest.approx((-180.4, 129.6), abs=0.05)


def test_binned_preparation_equals_binning_the_prepared_image():
    from psfkit.calibration.registration import _prepared, _prepared_binned
    from psfkit.numerics.resample import bin_image

    rng = np.random.default_rng(5)
    image = (rng.random((101, 130)) * 50 + 7).astype(np.float32)
    expected = bin_image(_prepared(image), 2)
    np.testing.assert_allclose(_prepared_binned(image, 2), expected, rtol=0, atol=1e-14)


def test_tukey_window_equals_scipys():
    from scipy.signal.windows import tukey

    from psfkit.numerics.windows import tukey_window

    for length in (0, 1, 2, 3, 10, 101, 540):
        for alpha in (0.0, 0.25, 0.3, 0.5, 1.0, 1.5):
            np.testing.assert_allclose(tukey_window(length, alpha), tukey(length, alpha),
                                       rtol=0, atol=1e-15)
