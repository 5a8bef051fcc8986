"""Angular-spectrum propagation against analytic optics."""

import numpy as np
import pytest

from psfkit.simulate.propagation import chief_ray_shift, oblique_transfer_function
from tests.helpers.optics import fresnel_transfer_anisotropic, propagate


def _gaussian(shape, pitch, w0, x0=0.0, y0=0.0):
    y = (np.arange(shape[0]) - shape[0] / 2) * pitch
    x = (np.arange(shape[1]) - shape[1] / 2) * pitch
    return np.exp(-((x[None] - x0) ** 2 + (y[:, None] - y0) ** 2) / w0**2), x, y


def test_gaussian_beam_width_matches_analytic_formula():
    """On-axis: w(z) = w0·sqrt(1 + (z/zR)²), zR = π w0²/λ (paraxial beam, w0 ≫ λ)."""
    lam, pitch, w0, z = 0.5, 2.0, 60.0, 40_000.0
    u0, x, _y = _gaussian((512, 512), pitch, w0)
    u = propagate(u0.astype(np.complex128),
                  oblique_transfer_function(u0.shape, pitch, lam, z))
    intensity = np.abs(u) ** 2
    zr = np.pi * w0**2 / lam
    w_expected = w0 * np.sqrt(1 + (z / zr) ** 2)
    # second moment of |u|² = exp(-2 r²/w²) is w²/4 per axis
    profile = intensity.sum(axis=0)
    w_measured = 2 * np.sqrt(np.sum(profile * x**2) / np.sum(profile))
    assert w_measured == pytest.approx(w_expected, rel=2e-3)
    assert intensity.sum() == pytest.approx(np.sum(u0**2), rel=1e-6)  # energy (Parseval)


@pytest.mark.parametrize("alpha,beta", [(0.1, 0.0), (0.0, -0.15), (0.12, 0.09)])
def test_residual_shift_moves_envelope_exactly(alpha, beta):
    """The transfer function applies the requested residual shift (centroid moves by r)."""
    lam, pitch, w0 = 0.5, 2.0, 40.0
    u0, x, y = _gaussian((256, 256), pitch, w0)
    r = (3.3, -1.7)
    u = propagate(u0.astype(np.complex128),
                  oblique_transfer_function(u0.shape, pitch, lam, 2000.0, alpha, beta, r))
    intensity = np.abs(u) ** 2
    cx = np.sum(intensity.sum(axis=0) * x) / intensity.sum()
    cy = np.sum(intensity.sum(axis=1) * y) / intensity.sum()
    assert cx == pytest.approx(r[0], abs=0.02)
    assert cy == pytest.approx(r[1], abs=0.02)


def test_chief_ray_shift_is_d_tan_theta():
    theta = np.deg2rad(10.0)
    sx, sy = chief_ray_shift(5000.0, np.sin(theta), 0.0)
    assert sx == pytest.approx(5000.0 * np.tan(theta), rel=1e-12)
    assert sy == 0.0


def test_oblique_propagation_equals_anisotropic_fresnel_for_a_smooth_beam():
    """Second-order content of H(g + f0): distances d/cos³θ (tangential), d/cosθ (sagittal)."""
    lam, pitch, w0, d = 0.5, 1.0, 25.0, 20_000.0
    theta, azimuth = np.deg2rad(15.0), np.deg2rad(30.0)
    alpha, beta = np.sin(theta) * np.cos(azimuth), np.sin(theta) * np.sin(azimuth)
    u0, _, _ = _gaussian((512, 512), pitch, w0)
    u0 = u0.astype(np.complex128)
    exact = np.abs(propagate(u0, oblique_transfer_function(u0.shape, pitch, lam, d, alpha,
                                                           beta))) ** 2
    cos_t = np.sqrt(1 - alpha**2 - beta**2)
    model = np.abs(propagate(u0, fresnel_transfer_anisotropic(
        u0.shape, pitch, lam, d / cos_t**3, d / cos_t, azimuth))) ** 2
    isotropic = np.abs(propagate(u0, fresnel_transfer_anisotropic(
        u0.shape, pitch, lam, d, d, azimuth))) ** 2
    err_model = np.linalg.norm(exact - model) / np.linalg.norm(exact)
    err_iso = np.linalg.norm(exact - isotropic) / np.linalg.norm(exact)
    assert err_model < 0.005
    assert err_iso > 20 * err_model
