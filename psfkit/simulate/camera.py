r"""The virtual bench: a simulated diffuser camera whose PSF really varies over the field.

Optics (scalar, thin element): a point source on a monitor at distance :math:`z` sends a
spherical (or plane) wave onto a thin random phase diffuser behind a finite aperture,
propagated over the gap :math:`d` with the exact angular-spectrum transfer function on the
frequency grid shifted by the source's carrier (:mod:`psfkit.simulate.propagation`). The
off-axis shift (:math:`d\tan\theta`), oblique astigmatism (:math:`d/\cos^3\theta` tangential,
:math:`d/\cos\theta` sagittal) and magnification changes all come out of the propagation.

Coordinates (``docs/architecture.md``): sensor rows ``v`` (down), columns ``u`` (right), axis
at the sensor centre; a source at monitor ``+x`` moves the PSF to ``-u``. The on-axis
noise-free PSF of a channel sums to 1, an off-axis one to ``gain(θ)`` (cos⁴ by default).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import scipy.fft as sfft

from psfkit.errors import ConfigurationError, PsfkitError
from psfkit.io.validation import bounded_size
from psfkit.numerics.resample import bin_image
from psfkit.simulate.bench_config import CHANNEL_NAMES, BenchConfig
from psfkit.simulate.diffuser import (
    DiffuserSurface,
    caustic_correlation_length,
    slope_rms_for_angle,
)
from psfkit.simulate.propagation import (
    box_blur,
    chief_ray_shift,
    oblique_transfer_function,
    unit_phasor,
)
from psfkit.simulate.propagation_torch import resolve_backend
from psfkit.simulate.psf_patch import PsfPatch, place_patch, translate_pixels
from psfkit.simulate.sensor import relative_illumination

if TYPE_CHECKING:
    from psfkit.simulate.propagation_torch import TorchOptics

MAX_PROPAGATION_PIXELS = 2**26   # samples of one propagation grid (complex128: 1 GB)


def _fast_block(min_pixels: int, parity: int, q: int) -> int:
    """Smallest block size >= ``min_pixels``, given parity, FFT-friendly ``q·n``."""
    n = max(min_pixels, 2)
    while True:
        if (n - parity) % 2 == 0 and sfft.next_fast_len(q * n) == q * n:
            return n
        n += 1


def _aperture_profile(coords_um: np.ndarray, size_um: float, pitch_um: float) -> np.ndarray:
    """Fraction of each sample cell inside ``|x| <= size/2`` (anti-aliased hard edge)."""
    half = size_um / 2.0
    lo = np.maximum(coords_um - pitch_um / 2.0, -half)
    hi = np.minimum(coords_um + pitch_um / 2.0, half)
    return np.clip((hi - lo) / pitch_um, 0.0, 1.0)


class VirtualCamera:
    """A simulated diffuser camera; :meth:`psf` gives the noise-free PSF at any field point.

    Parameters
    ----------
    config : BenchConfig
        All physical parameters; the diffuser surface is drawn from ``config.seed``.
    surface : callable, optional
        ``surface(y_um, x_um) -> height_um`` on the grid of two increasing 1-D coordinate arrays
        (relative to the axis); replaces the random diffuser.
    backend : {"auto", "torch", "numpy"}
        ``"torch"``: batched float32 FFTs (:mod:`psfkit.simulate.propagation_torch`, CUDA if
        present; ~1e-5 relative to numpy); ``"numpy"``: the reference path (scipy.fft, float64
        phases); ``"auto"``: torch where importable.
    device : str, optional
        torch device (default CUDA if available, else CPU).

    Examples
    --------
    >>> cam = VirtualCamera(BenchConfig(downsample=8))
    >>> psf = cam.psf((3.0, -2.0))          # (C, H, W), field angles in degrees
    >>> cam.true_shift_px((3.0, -2.0))      # (du, dv) relative to the on-axis PSF
    """

    def __init__(self, config: BenchConfig | None = None,
                 surface: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                 backend: str = "auto", device: str | None = None) -> None:
        self.config = config = config or BenchConfig()
        self.backend = resolve_backend(backend)
        self.sensor_shape = (config.sensor_shape[0] // config.downsample,
                             config.sensor_shape[1] // config.downsample)
        self.pixel_um = config.pixel_pitch_um * config.downsample
        self.gap_um = config.gap_mm * 1e3
        self.z_um = config.monitor_distance_mm * 1e3
        self.wavelengths_um = tuple(w * 1e-3 for w in config.wavelengths_nm)
        self.channels = CHANNEL_NAMES[len(self.wavelengths_um)]

        sigma_angle = np.deg2rad(config.diffusion_angle_deg) / 2.3548200450309493
        aperture_um = (config.aperture_mm[0] * 1e3, config.aperture_mm[1] * 1e3)
        # Widest angle (relative to the chief ray) carrying light: 4.5σ of the diffuser plus
        # the divergence of the spherical wave across the aperture.
        divergence = (0.5 * max(aperture_um) / self.z_um) if config.spherical_source else 0.0
        max_angle = 4.5 * sigma_angle + divergence
        if config.oversample is None:
            nyquist_pitch = min(self.wavelengths_um) / (2.0 * np.sin(max_angle))
            self.oversample = max(2, int(np.ceil(self.pixel_um / nyquist_pitch)))
        else:
            self.oversample = int(config.oversample)
        q = self.oversample
        self.sim_pitch_um = self.pixel_um / q

        # Block: aperture + spread of the scattered light + astigmatic growth at the FoV edge
        margin_um = self.gap_um * 1.15 * np.tan(max_angle) + 4 * self.pixel_um
        blur_um = self.source_blur_um()
        minimum = tuple(int(np.ceil((a + 2 * margin_um + blur_um) / self.pixel_um))
                        for a in aperture_um)
        # the propagation grid follows from the geometry: sized before anything is allocated
        # (a wide diffusion angle or a long gap would otherwise run out of memory or time)
        try:
            bounded_size(tuple(q * m for m in minimum), "the virtual bench's propagation grid",
                         max_side=2**14, max_total=MAX_PROPAGATION_PIXELS)
        except PsfkitError as exc:
            raise ConfigurationError(f"{exc} (from gap_mm {config.gap_mm:g}, "
                                     f"diffusion_angle_deg {config.diffusion_angle_deg:g}, "
                                     f"aperture_mm {list(config.aperture_mm)}, oversample {q}); "
                                     "use a smaller gap, angle or aperture") from None
        self.block_pixels = tuple(_fast_block(m, s % 2, q)
                                  for m, s in zip(minimum, self.sensor_shape, strict=True))
        n_y, n_x = (q * b for b in self.block_pixels)
        self.y_um = (np.arange(n_y) - (n_y - 1) / 2.0) * self.sim_pitch_um
        self.x_um = (np.arange(n_x) - (n_x - 1) / 2.0) * self.sim_pitch_um

        ell = config.correlation_length_um or caustic_correlation_length(
            config.diffusion_angle_deg, self.gap_um)
        self.correlation_length_um = ell
        self.diffuser = DiffuserSurface.generate(
            extent_um=(aperture_um[0] + 4 * ell, aperture_um[1] + 4 * ell),
            correlation_length_um=ell,
            slope_rms=slope_rms_for_angle(config.diffusion_angle_deg, config.refractive_index),
            seed=config.seed)
        self._height_um = (surface or self.diffuser.height)(self.y_um, self.x_um)
        if self._height_um.shape != (self.y_um.size, self.x_um.size):
            raise ConfigurationError(f"surface returned shape {self._height_um.shape}, expected "
                                     f"{(self.y_um.size, self.x_um.size)}")
        aperture = (_aperture_profile(self.y_um, aperture_um[0], self.sim_pitch_um)[:, None]
                    * _aperture_profile(self.x_um, aperture_um[1], self.sim_pitch_um)[None])
        self._aperture = aperture.astype(np.float32)
        self._aperture_power = float(np.sum(aperture**2))
        self._plane_spectra: dict[int, np.ndarray] = {}
        self._torch: TorchOptics | None = None
        if self.backend == "torch":
            from psfkit.simulate.propagation_torch import TorchOptics

            self._torch = TorchOptics(
                self.x_um, self.y_um, (config.refractive_index - 1.0) * self._height_um,
                aperture, self.wavelengths_um, self.gap_um, self.z_um, self.sim_pitch_um,
                q, config.spherical_source, device)

    @property
    def device_type(self) -> str:
        """``"cpu"`` or ``"cuda"``: where the optics run."""
        return self._torch.device.type if self._torch is not None else "cpu"

    # ------------------------------------------------------------------ geometry

    @property
    def magnification(self) -> float:
        """Sensor pixels of PSF shift per monitor pixel of source displacement."""
        return self.gap_um * self.config.monitor_pixel_pitch_mm * 1e3 / (self.z_um * self.pixel_um)

    def field_from_monitor(self, x_px: float | np.ndarray, y_px: float | np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
        """Field angles ``(θx, θy)`` in degrees of monitor positions (pixels from the axis)."""
        pitch_um = self.config.monitor_pixel_pitch_mm * 1e3
        return (np.rad2deg(np.arctan(np.asarray(x_px) * pitch_um / self.z_um)),
                np.rad2deg(np.arctan(np.asarray(y_px) * pitch_um / self.z_um)))

    def _source_position_um(self, field_deg: tuple[float, float]) -> tuple[float, float]:
        tx, ty = np.deg2rad(field_deg[0]), np.deg2rad(field_deg[1])
        return self.z_um * np.tan(tx), self.z_um * np.tan(ty)

    def direction_cosines(self, field_deg: tuple[float, float]) -> tuple[float, float, float]:
        """Direction ``(α, β, γ)`` of the chief ray from a source at ``field_deg``."""
        xs, ys = self._source_position_um(field_deg)
        r0 = np.sqrt(xs**2 + ys**2 + self.z_um**2)
        return -xs / r0, -ys / r0, self.z_um / r0

    def true_shift_px(self, field_deg: tuple[float, float]) -> tuple[float, float]:
        """Exact chief-ray shift ``(du, dv)`` in sensor pixels: ``−d·tanθ / pixel``."""
        alpha, beta, _ = self.direction_cosines(field_deg)
        sx, sy = chief_ray_shift(self.gap_um, alpha, beta)
        return sx / self.pixel_um + 0.0, sy / self.pixel_um + 0.0  # + 0.0: no negative zeros

    def gain(self, field_deg: tuple[float, float]) -> float:
        """Relative illumination of the source, 1 on axis (always 1 if ``field_free``)."""
        if self.config.field_free:
            return 1.0
        return float(relative_illumination(self.direction_cosines(field_deg)[2],
                                           self.config.vignetting_exponent))

    def source_blur_um(self) -> float:
        """Width on the sensor of the displayed square source's geometric image (µm)."""
        return (self.gap_um * self.config.source_size_px * self.config.monitor_pixel_pitch_mm
                * 1e3 / self.z_um)

    # ------------------------------------------------------------------ optics

    def optical_path_um(self, field_deg: tuple[float, float]) -> np.ndarray:
        """Wavelength-independent optical path (µm) on the optical grid, carrier removed:
        ``(n−1)·h(x, y) + (R − R0 − α x − β y)`` (the second term for a spherical source only)."""
        opl = (self.config.refractive_index - 1.0) * self._height_um
        if not self.config.spherical_source:
            return opl
        xs, ys = self._source_position_um(field_deg)
        r0 = np.sqrt(xs**2 + ys**2 + self.z_um**2)
        x = self.x_um[None, :]
        y = self.y_um[:, None]
        r = np.sqrt((x - xs) ** 2 + (y - ys) ** 2 + self.z_um**2)
        # R − R0 − αx − βy written without cancellation
        return opl + ((x * x - 2 * x * xs) + (y * y - 2 * y * ys)) / (r + r0) \
            + (x * xs + y * ys) / r0

    def envelope(self, field_deg: tuple[float, float], channel: int,
                 optical_path_um: np.ndarray | None = None) -> np.ndarray:
        """``aperture · exp(i 2π/λ · optical_path)`` (complex64) behind the diffuser, carrier
        removed."""
        if optical_path_um is None:
            optical_path_um = self.optical_path_um(field_deg)
        k = 2.0 * np.pi / self.wavelengths_um[channel]
        return self._aperture * unit_phasor(k * optical_path_um)

    def _spectrum(self, field_deg: tuple[float, float], channel: int,
                  optical_path_um: np.ndarray | None) -> np.ndarray:
        if self.config.spherical_source:
            return sfft.fft2(self.envelope(field_deg, channel, optical_path_um), workers=-1)
        if channel not in self._plane_spectra:
            self._plane_spectra[channel] = sfft.fft2(self.envelope((0.0, 0.0), channel),
                                                     workers=-1)
        return self._plane_spectra[channel]

    def psf_patch(self, field_deg: tuple[float, float], subpixel_shift: bool = True) -> PsfPatch:
        """Noise-free PSF of a source at ``field_deg`` ``(θx, θy)`` degrees on the block around its
        chief ray.

        ``subpixel_shift=False`` omits the chief-ray shift's sub-pixel part (the PSF in the frame
        moving with the chief ray). Returns a :class:`PsfPatch` in relative irradiance.
        """
        du, dv = self.true_shift_px(field_deg)
        nu, nv = int(np.round(du)), int(np.round(dv))
        if self.config.field_free:
            out = self._optics_patch((0.0, 0.0), (0.0, 0.0))
            if subpixel_shift and (du != nu or dv != nv):
                out = translate_pixels(out, (du - nu, dv - nv))
        else:
            residual_um = ((du - nu) * self.pixel_um, (dv - nv) * self.pixel_um) \
                if subpixel_shift else (0.0, 0.0)
            out = self._optics_patch(field_deg, residual_um)
        v0 = (self.sensor_shape[0] - self.block_pixels[0]) // 2 + nv
        u0 = (self.sensor_shape[1] - self.block_pixels[1]) // 2 + nu
        return PsfPatch(image=out, offset=(v0, u0), shift_px=(du, dv))

    def _optics_patch(self, field_deg: tuple[float, float],
                      residual_um: tuple[float, float]) -> np.ndarray:
        """The block's ``(C, h, w)`` PSF of a source whose chief ray lands ``residual_um`` from the
        block's centre pixel."""
        alpha, beta, _ = self.direction_cosines(field_deg)
        scale = self.gain(field_deg) / self._aperture_power
        blur_px = self.source_blur_um() / self.pixel_um
        if self._torch is None:
            return self._numpy_patch(field_deg, alpha, beta, residual_um, scale, blur_px)
        from psfkit.simulate.propagation_torch import to_numpy

        out = self._torch.intensity(self._source_position_um(field_deg), alpha, beta,
                                    residual_um)
        out *= scale
        if blur_px > 0:
            out = self._torch.box_blur(out, blur_px)
        return to_numpy(out)

    def _numpy_patch(self, field_deg: tuple[float, float], alpha: float, beta: float,
                     residual_um: tuple[float, float], scale: float, blur_px: float
                     ) -> np.ndarray:
        """The block's ``(C, h, w)`` float64 PSF with scipy.fft (the reference path)."""
        shape = (self.y_um.size, self.x_um.size)
        opl = self.optical_path_um(field_deg) if self.config.spherical_source else None
        out = np.empty((len(self.channels), *self.block_pixels), dtype=np.float64)
        for c, lam in enumerate(self.wavelengths_um):
            transfer = oblique_transfer_function(shape, self.sim_pitch_um, lam, self.gap_um,
                                                 alpha, beta, residual_um)
            transfer *= self._spectrum(field_deg, c, opl)
            field_at_sensor = sfft.ifft2(transfer, workers=-1, overwrite_x=True)
            # sensor-pixel integration of the oversampled intensity
            intensity = bin_image(np.abs(field_at_sensor) ** 2, self.oversample, exact=True)
            out[c] = intensity * scale
        return box_blur(out, blur_px) if blur_px > 0 else out

    def psf(self, field_deg: tuple[float, float]) -> np.ndarray:
        """Noise-free PSF on the sensor, ``(C, H, W)`` float32, relative irradiance."""
        return place_patch(self.psf_patch(field_deg), self.sensor_shape)
