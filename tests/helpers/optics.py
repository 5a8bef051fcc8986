"""The paraxial reference model of oblique propagation that the bench simulation
(:mod:`psfkit.simulate.propagation`) is checked against."""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from psfkit.simulate.propagation import frequency_grid


def fresnel_transfer_anisotropic(shape: tuple[int, int], pitch_um: float,
                                 wavelength_um: float, distance_tangential_um: float,
                                 distance_sagittal_um: float, azimuth_rad: float) -> np.ndarray:
    r"""Paraxial transfer function with different distances along two orthogonal directions.

    :math:`H(g) = \exp(-i\pi\lambda(d_t g_t^2 + d_s g_s^2))`, with :math:`g_t` the frequency
    component along the unit vector at ``azimuth_rad`` (measured from +x towards +y) and
    :math:`g_s` the component perpendicular to it. With ``d_t = d/cos³θ`` and ``d_s = d/cosθ``
    this is the second-order model of oblique propagation at field angle θ.
    """
    gy, gx = frequency_grid(shape, pitch_um)
    c, s = np.cos(azimuth_rad), np.sin(azimuth_rad)
    g_t = c * gx + s * gy
    g_s = -s * gx + c * gy
    return np.exp(-1j * np.pi * wavelength_um * (distance_tangential_um * g_t**2
                                                 + distance_sagittal_um * g_s**2))


def propagate(field: np.ndarray, transfer: np.ndarray, workers: int | None = None) -> np.ndarray:
    """Apply a transfer function (FFT order) to a complex field: ``IFFT(FFT(field)·H)``."""
    return sfft.ifft2(sfft.fft2(field, workers=workers) * transfer, workers=workers)
