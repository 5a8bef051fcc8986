"""Image-sensor model: relative illumination, pixel integration, Poisson–Gaussian noise,
black level, bit depth and saturation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfkit.errors import ConfigurationError


def relative_illumination(cos_theta: float | np.ndarray, exponent: float = 4.0
                          ) -> float | np.ndarray:
    """Vignetting gain ``cos(θ)**exponent`` of a source at field angle θ (cos⁴ law by default;
    ``exponent`` lets a lab match a measured fall-off)."""
    return np.asarray(cos_theta, dtype=np.float64) ** exponent


@dataclass(frozen=True)
class SensorModel:
    """Photon-to-digital conversion of one exposure.

    Attributes
    ----------
    full_well_e : float
        Electrons at the top of the digital range (above black level).
    read_noise_e : float
        Gaussian read noise, electrons RMS.
    bit_depth : int
        ADC resolution; values are stored MSB-aligned in 16-bit files (12-bit data × 16).
    black_level_dn : float
        Offset added before quantisation, in ADC units.
    quantum_efficiency : tuple of float
        Per-channel fraction of photons detected (R, G, B); mono sensors use the first.
    """

    full_well_e: float = 10500.0
    read_noise_e: float = 2.5
    bit_depth: int = 12
    black_level_dn: float = 64.0
    quantum_efficiency: tuple[float, ...] = (0.52, 0.64, 0.46)

    def __post_init__(self) -> None:
        if not 8 <= self.bit_depth <= 16:
            raise ConfigurationError(f"bit_depth must be in 8..16, got {self.bit_depth}")
        if self.full_well_e <= 0 or self.read_noise_e < 0:
            raise ConfigurationError("full_well_e must be > 0 and read_noise_e >= 0")
        if not 0 <= self.black_level_dn < self.max_dn:
            raise ConfigurationError("black_level_dn must be in [0, 2**bit_depth - 1)")
        if not all(0 < q <= 1 for q in self.quantum_efficiency):
            raise ConfigurationError("quantum_efficiency values must be in (0, 1]")

    @property
    def max_dn(self) -> int:
        return 2**self.bit_depth - 1

    @property
    def container_scale(self) -> int:
        """Stored file units per ADC unit (MSB alignment in a 16-bit container)."""
        return 2 ** (16 - self.bit_depth)

    @property
    def electrons_per_dn(self) -> float:
        return self.full_well_e / (self.max_dn - self.black_level_dn)

    @property
    def black_level(self) -> float:
        """Black level in stored file units."""
        return self.black_level_dn * self.container_scale

    def qe(self, n_channels: int) -> np.ndarray:
        q = np.asarray(self.quantum_efficiency[:n_channels], dtype=np.float64)
        if q.size != n_channels:
            raise ConfigurationError(f"need {n_channels} quantum_efficiency values")
        return q

    def expected_file_units(self, electrons: np.ndarray) -> np.ndarray:
        """Noise-free signal above black level in stored file units (no clipping)."""
        return electrons * (self.container_scale / self.electrons_per_dn)

    def capture(self, electrons: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Simulate one raw frame from expected photo-electrons ``(C, H, W)``: Poisson shot noise,
        Gaussian read noise, black level, ADC rounding, clipping, MSB-aligned ``uint16``."""
        e = rng.poisson(np.maximum(electrons, 0.0)).astype(np.float64)
        if self.read_noise_e > 0:
            e += rng.normal(0.0, self.read_noise_e, size=e.shape)
        dn = np.clip(np.rint(e / self.electrons_per_dn + self.black_level_dn), 0, self.max_dn)
        return (dn * self.container_scale).astype(np.uint16)

    def capture_mean(self, electrons: np.ndarray, rng: np.random.Generator,
                     frames: int) -> tuple[np.ndarray, np.ndarray]:
        """The mean of ``frames`` independent raw frames (:meth:`capture`) of the same exposure.

        Parameters
        ----------
        electrons : numpy.ndarray
            ``(C, H, W)`` expected photo-electrons of one frame.
        rng : numpy.random.Generator
            Noise stream (the frames are drawn in order).
        frames : int
            Frames averaged, ≥ 1.

        Returns
        -------
        mean : numpy.ndarray
            ``(C, H, W)`` float32 mean in stored file units (black level included).
        saturated : numpy.ndarray
            ``(C, H, W)`` bool, at full scale in at least one frame.
        """
        if int(frames) != frames or frames < 1:
            raise ConfigurationError(f"frames must be an integer >= 1, got {frames}")
        full_scale = self.max_dn * self.container_scale
        total = np.zeros(np.shape(electrons), dtype=np.float64)
        saturated = np.zeros(np.shape(electrons), dtype=bool)
        for _ in range(int(frames)):
            raw = self.capture(electrons, rng)
            total += raw
            saturated |= raw >= full_scale
        return (total / frames).astype(np.float32), saturated
