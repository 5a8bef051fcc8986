"""The compact-PSF camera's parameters (:class:`CompactCamera`): checks, the true affine
field → shift map and the JSON form (see :mod:`research.compact_bench.scan`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from psfkit.errors import ConfigurationError
from psfkit.simulate.sensor import SensorModel


@dataclass(frozen=True)
class CompactCamera:
    """Parameters of the compact-PSF camera (see :mod:`research.compact_bench.scan`).

    Attributes
    ----------
    fwhm_px : float
        FWHM of the on-axis Airy PSF, px.
    width_growth : float
        Fractional FWHM increase at the field edge (∝ radius²).
    ellipticity : float
        Radial stretch − 1 at the field edge (∝ radius²).
    plate_scale_deg : float
        Field angle per pixel on axis, degrees.
    rotation_deg : float
        Rotation of the image on the detector.
    distortion_px : float
        Radial displacement at the field edge from cubic distortion, px (+: pincushion).
    axis_offset_px : (float, float)
        Optical axis ``(x, y)`` relative to the frame centre, px.
    peak_fraction : float
        Peak of the brightest (reference) source as a fraction of full well.
    brightness_range : float
        Brightest / faintest flux (log-uniform in between).
    background_e : float
        Uniform background per pixel, electrons.
    edge_margin_px : int
        Sources image at least this far inside the frame.
    sensor : SensorModel
        Noise, black level and bit depth (mono; fluxes are detected electrons).
    """

    fwhm_px: float = 3.0
    width_growth: float = 0.0
    ellipticity: float = 0.0
    plate_scale_deg: float = 0.005
    rotation_deg: float = 0.3
    distortion_px: float = 0.0
    axis_offset_px: tuple[float, float] = (0.3, -0.2)
    peak_fraction: float = 0.7
    brightness_range: float = 10.0
    background_e: float = 0.0
    edge_margin_px: int = 24
    sensor: SensorModel = field(default_factory=SensorModel)

    def __post_init__(self) -> None:
        if not 0.5 <= self.fwhm_px <= 64:
            raise ConfigurationError(f"fwhm_px must be in [0.5, 64], got {self.fwhm_px}")
        if self.width_growth < 0 or self.ellipticity < 0:
            raise ConfigurationError("width_growth and ellipticity must be >= 0")
        if not 0 < self.peak_fraction <= 1 or self.brightness_range < 1:
            raise ConfigurationError("peak_fraction must be in (0, 1], brightness_range >= 1")
        if self.plate_scale_deg <= 0 or self.background_e < 0 or self.edge_margin_px < 0:
            raise ConfigurationError("plate_scale_deg must be > 0, background_e and "
                                     "edge_margin_px >= 0")

    @property
    def magnification(self) -> float:
        """Sensor px per unit ``tan θ`` on axis."""
        return 1.0 / math.tan(math.radians(self.plate_scale_deg))

    def shift_matrix(self) -> np.ndarray:
        """The true affine map ``A`` (``shift = A · tan θ``, px), an inverted, rotated image."""
        rho = math.radians(self.rotation_deg)
        rotation = np.array([[math.cos(rho), -math.sin(rho)], [math.sin(rho), math.cos(rho)]])
        return -self.magnification * rotation

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["axis_offset_px"] = list(self.axis_offset_px)
        out["sensor"] = {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in asdict(self.sensor).items()}
        return out

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> CompactCamera:
        doc = dict(doc)
        sensor = dict(doc.pop("sensor"))
        sensor["quantum_efficiency"] = tuple(sensor["quantum_efficiency"])
        doc["axis_offset_px"] = tuple(doc["axis_offset_px"])
        return cls(sensor=SensorModel(**sensor), **doc)
