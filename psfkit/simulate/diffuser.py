r"""A thin random phase diffuser: smooth random surface height with a set diffusion angle.

The surface is a Gaussian random field with a Gaussian autocorrelation
:math:`C(r) = \sigma_h^2 e^{-r^2/\ell^2}` (correlation length ℓ). For a thin element of
refractive index n, a ray is deflected by :math:`(n-1)\nabla h`; with Gaussian slopes of
RMS :math:`\sigma_s` per axis the scattered light has a Gaussian angular profile of standard
deviation :math:`\sigma_a = (n-1)\sigma_s` per axis, whose full width at half maximum is the
*diffusion angle* quoted for engineered diffusers:
:math:`\theta_\mathrm{FWHM} = 2\sqrt{2\ln 2}\,\sigma_a`.

The surface is generated on a coarse *master* grid fixed in the diffuser's own frame
(ℓ/8 spacing) and evaluated anywhere by cubic-spline interpolation, so the same seed gives
the same physical diffuser whatever the simulation sampling (full resolution or downsampled).
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

    For the Gaussian surface above the RMS curvature is :math:`\sqrt{6}\sigma_s/\ell`, so a
    typical surface bump focuses light at :math:`f = \ell / (\sqrt6\,\sigma_a)`; choosing
    :math:`f` equal to the diffuser–sensor gap gives the sharp caustic network of a DiffuserCam.
    """
    sigma_angle = np.deg2rad(diffusion_angle_deg) / FWHM_PER_SIGMA
    return float(np.sqrt(6.0) * sigma_angle * focus_distance_um)


@dataclass(frozen=True)
class DiffuserSurface:
    """Random surface height (µm) on a master grid centred on the diffuser's axis.

    Use :meth:`generate` to create one and :meth:`height` to evaluate it.
    """

    master: np.ndarray          # (ny, nx) height samples, µm
    master_pitch_um: float
    correlation_length_um: float
    slope_rms: float

    @classmethod
    def generate(cls, extent_um: tuple[float, float], correlation_length_um: float,
                 slope_rms: float, seed: int) -> DiffuserSurface:
        """Draw a surface covering at least ``extent_um = (height, width)`` around the axis.

        Parameters
        ----------
        extent_um : (float, float)
            Physical size (µm) that must be covered, centred on the axis.
        correlation_length_um : float
            ℓ, the 1/e radius of the height autocorrelation.
        slope_rms : float
            RMS slope per axis (dimensionless), e.g. from :func:`slope_rms_for_angle`.
        seed : int
            Random seed; the same seed and parameters give the same surface.
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
        """Surface height (µm) on the grid spanned by 1-D coordinates ``y_um`` and ``x_um``.

        Coordinates are relative to the diffuser axis (the master grid's centre) and must be
        increasing; the result has shape ``(len(y_um), len(x_um))``.
        """
        ny, nx = self.master.shape
        my = (np.arange(ny) - (ny - 1) / 2.0) * self.master_pitch_um
        mx = (np.arange(nx) - (nx - 1) / 2.0) * self.master_pitch_um
        spline = interpolate.RectBivariateSpline(my, mx, self.master, kx=3, ky=3, s=0)
        return spline(np.asarray(y_um, dtype=np.float64), np.asarray(x_um, dtype=np.float64))
