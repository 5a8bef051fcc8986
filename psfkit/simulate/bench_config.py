"""The virtual bench's configuration: :class:`BenchConfig`, its checks (the command-line flags'
ranges apply wherever a value comes from) and its dictionary form for run files.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from psfkit.errors import ConfigurationError, PsfkitError
from psfkit.io.flag_ranges import flag_range
from psfkit.simulate.sensor import SensorModel

CHANNEL_NAMES = {1: ("L",), 3: ("R", "G", "B")}
#: BenchConfig fields set by command-line flags: the flags' ranges (``psfkit.io.flag_ranges.FLAGS``)
#: apply to them wherever they come from
BENCH_FLAGS = {"diffusion_angle_deg": "--diffusion-angle", "gap_mm": "--gap-mm",
               "peak_fraction": "--peak-fraction", "seed": "--seed",
               "downsample": "--downsample"}


@dataclass(frozen=True)
class BenchConfig:
    """Parameters of the virtual diffuser camera (defaults follow the EK-DUN prototype).

    Attributes
    ----------
    diffusion_angle_deg : float
        FWHM of the diffuser's scattering profile.
    refractive_index : float
        Of the diffuser material.
    correlation_length_um : float or None
        Of the surface; ``None``: caustics focused at the sensor
        (:func:`~psfkit.simulate.diffuser.caustic_correlation_length`).
    aperture_mm : (float, float)
        ``(height, width)`` of the rectangular aperture.
    gap_mm : float
        Diffuser–sensor distance ``d`` (the default maps the monitor FoV onto the sensor).
    wavelengths_nm : tuple of float
        One per channel (R, G, B); a single value simulates a mono camera.
    monitor_distance_mm, monitor_pixel_pitch_mm : float
        Monitor geometry (a 24" full-HD panel at 50 cm).
    fov_monitor_px : (int, int)
        ``(height, width)`` of the field of view on the monitor, monitor pixels.
    source_size_px : float
        Side of the displayed square source, monitor pixels (0: an ideal point).
    spherical_source : bool
        Spherical wave from the monitor distance (True) or a plane wave.
    sensor_shape : (int, int)
        ``(H, W)`` at full resolution; ``pixel_pitch_um`` at full resolution.
    downsample : int
        Binning factor for fast runs (larger pixels; the optics are unchanged).
    oversample : int or None
        Optical samples per pixel and axis; ``None``: the smallest Nyquist one (at least 2).
    vignetting_exponent : float
        Relative illumination ``cos(θ)**exponent``.
    field_free : bool
        No field variation (a test facility): every PSF is the pixel-sampled on-axis PSF
        translated by the chief-ray shift, without vignetting.
    sensor : SensorModel
        Noise, black level, bit depth, saturation.
    peak_fraction : float
        The brightest on-axis pixel reaches this fraction of full well (above 1 saturates).
    seed : int
        Seed of the diffuser surface and of the sensor noise.
    """

    diffusion_angle_deg: float = 1.0
    refractive_index: float = 1.5
    correlation_length_um: float | None = None
    aperture_mm: tuple[float, float] = (2.6, 2.6)
    gap_mm: float = 14.6
    wavelengths_nm: tuple[float, ...] = (610.0, 530.0, 470.0)
    monitor_distance_mm: float = 500.0
    monitor_pixel_pitch_mm: float = 0.2768
    fov_monitor_px: tuple[int, int] = (442, 614)
    source_size_px: float = 1.0
    spherical_source: bool = True
    sensor_shape: tuple[int, int] = (1080, 1440)
    pixel_pitch_um: float = 3.45
    downsample: int = 1
    oversample: int | None = None
    vignetting_exponent: float = 4.0
    field_free: bool = False
    sensor: SensorModel = field(default_factory=SensorModel)
    peak_fraction: float = 0.8
    seed: int = 0

    def __post_init__(self) -> None:
        self._check_flag_ranges()
        self._check_optics()
        self._check_sampling()

    def _check_flag_ranges(self) -> None:
        # the ranges of the command-line flags (one table), for --bench-config files too
        for name, flag_name in BENCH_FLAGS.items():
            try:
                flag_range(flag_name).check(getattr(self, name), f"{name} ({flag_name})")
            except PsfkitError as exc:
                raise ConfigurationError(str(exc)) from None

    def _check_optics(self) -> None:
        # (the flags' ranges already require a positive angle, gap and peak fraction)
        for name in ("monitor_distance_mm", "monitor_pixel_pitch_mm", "pixel_pitch_um"):
            if not getattr(self, name) > 0:
                raise ConfigurationError(f"{name} must be positive, got {getattr(self, name)}")
        if self.refractive_index <= 1.0:
            raise ConfigurationError("refractive_index must be > 1")
        if len(self.wavelengths_nm) not in CHANNEL_NAMES or min(self.wavelengths_nm) <= 0:
            raise ConfigurationError("wavelengths_nm needs 1 (mono) or 3 (RGB) positive values")
        if min(self.aperture_mm) <= 0 or min(self.fov_monitor_px) <= 0:
            raise ConfigurationError("aperture_mm and fov_monitor_px must be positive")

    def _check_sampling(self) -> None:
        if not isinstance(self.downsample, int) or self.downsample < 1:
            raise ConfigurationError(f"downsample must be an integer >= 1, got {self.downsample}")
        h, w = self.sensor_shape
        if h // self.downsample < 16 or w // self.downsample < 16:
            raise ConfigurationError(f"downsample {self.downsample} leaves fewer than 16 pixels")
        if self.oversample is not None and self.oversample < 1:
            raise ConfigurationError("oversample must be >= 1")
        if self.correlation_length_um is not None and self.correlation_length_um <= 0:
            raise ConfigurationError("correlation_length_um must be positive")
        if self.source_size_px < 0:
            raise ConfigurationError("source_size_px must be >= 0")

    def to_dict(self) -> dict:
        """JSON-friendly description of every parameter."""
        return {name: list(value) if isinstance(value, tuple) else value
                for name, value in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict) -> BenchConfig:
        """Inverse of :meth:`to_dict` (unknown keys are an error)."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ConfigurationError(f"unknown bench parameter(s): {', '.join(sorted(unknown))}")
        kwargs = dict(data)
        if isinstance(kwargs.get("sensor"), dict):
            sensor = dict(kwargs["sensor"])
            if "quantum_efficiency" in sensor:
                sensor["quantum_efficiency"] = tuple(sensor["quantum_efficiency"])
            kwargs["sensor"] = SensorModel(**sensor)
        for name in ("aperture_mm", "wavelengths_nm", "fov_monitor_px", "sensor_shape"):
            if name in kwargs:
                kwargs[name] = tuple(kwargs[name])
        return cls(**kwargs)
