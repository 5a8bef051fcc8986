r"""A thin random phase diffuser: smooth random surface height with a set diffusion angle.

The surface is a Gaussian random field with autocorrelation
:math:`C(r) = \sigma_h^2 e^{-r^2/\ell^2}`. A thin element deflects rays by
:math:`(n-1)\nabla h`, so slopes of RMS :math:`\sigma_s` per axis give a Gaussian angular profile
of :math:`\sigma_a = (n-1)\sigma_s`, whose FWHM is the *diffusion angle*
:math:`\theta_\mathrm{FWHM} = 2\sqrt{2\ln 2}\,\sigma_a`. The surface lives on a master grid
(ℓ/8 spacing) in the diffuser's frame and is spline-interpolated, so a seed gives the same
physical diffuser at any sampling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import interpolate, ndimage

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def slope_rms_for_angle(diffusion_angle_deg: float, refractive_index: float) -> float:
    """RMS surface slope per axis giving a diffusion angle (FWHM, degrees)."""
    sigma_angle = np.deg2rad(diffusion_angle_deg) / FWHM_PER_SIGMA
    return float(sigma_angle / (refractive_index - 1.0))


def caustic_correlation_length(diffusion_angle_deg: float, focus_distance_um: float) -> float:
    r"""Correlation length (µm) that brings the typical caustic into focus at a distance.

    The RMS curvature is :math:`\sqrt{6}\sigma_s/\ell`, so a bump focuses at
    :math:`f = \ell / (\sqrt6\,\sigma_a)`; :math:`f` = the gap gives a DiffuserCam's sharp caustics.
    """
    sigma_angle = np.deg2rad(diffusion_angle_deg) / FWHM_PER_SIGMA
    return float(np.sqrt(6.0) * sigma_angle * focus_distance_um)


@dataclass(frozen=True)
class DiffuserSurface:
    """Random surface height (µm) on a master grid centred on the axis (:meth:`generate`,
    :meth:`height`)."""

    master: np.ndarray          # (ny, nx) height samples, µm
    master_pitch_um: float
    correlation_length_um: float
    slope_rms: float

    @classmethod
    def generate(cls, extent_um: tuple[float, float], correlation_length_um: float,
                 slope_rms: float, seed: int) -> DiffuserSurface:
        """Draw a surface covering at least ``extent_um`` ``(height, width)`` µm around the axis.

        Parameters
        ----------
        extent_um : (float, float)
        correlation_length_um : float
            ℓ, the 1/e radius of the height autocorrelation.
        slope_rms : float
            RMS slope per axis (:func:`slope_rms_for_angle`).
        seed : int
            The same seed and parameters give the same surface.
        """
        pitch = correlation_length_um / 8.0
        shape = tuple(int(np.ceil(e / pitch)) + 16 for e in extent_um)
        rng = np.random.default_rng(seed)
        noise = rng.standard_normal(shape)
        # white noise filtered by a Gaussian of std s has autocorrelation exp(-r²/(4 s²))
        smooth = ndimage.gaussian_filter(noise, sigma=correlation_length_um / 2.0 / pitch,
                                         mode="wrap")
        gy, gx = np.gradient(smooth, pitch)
        measured = np.sqrt(0.5 * (np.mean(gx**2) + np.mean(gy**2)))
        master = smooth * (slope_rms / measured)
        return cls(master=master, master_pitch_um=pitch,
                   correlation_length_um=correlation_length_um, slope_rms=slope_rms)

    def height(self, y_um: np.ndarray, x_um: np.ndarray) -> np.ndarray:
        """Surface height (µm) ``(len(y_um), len(x_um))`` on the grid of increasing 1-D coordinates
        relative to the axis."""
        ny, nx = self.master.shape
        my = (np.arange(ny) - (ny - 1) / 2.0) * self.master_pitch_um
        mx = (np.arange(nx) - (nx - 1) / 2.0) * self.master_pitch_um
        spline = interpolate.RectBivariateSpline(my, mx, self.master, kx=3, ky=3, s=0)
        return spline(np.asarray(y_um, dtype=np.float64), np.asarray(x_um, dtype=np.float64))
