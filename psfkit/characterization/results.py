"""What a characterization of a PSF grid holds (options, per-position numbers, fits, verdict,
coverage, small images): read by the report and figures without the measurement code."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psfkit.calibration.alignment import (
    MIN_QUALITY,
    REJECTION_REASONS,
    RELIABLE_OVERLAP,
    ExcludedPosition,
)
from psfkit.calibration.gain import GainFit
from psfkit.calibration.preprocess import PreprocessOptions
from psfkit.calibration.shift_map import ShiftMapFit
from psfkit.calibration.warp import FLOW_METHODS, GrowthFit
from psfkit.errors import ConfigurationError
from psfkit.fitting.verdict import Verdict
from psfkit.io.grid import FULL_LATTICE
from psfkit.numerics.significance import Z_SIGNIFICANT, Estimate, alpha, undetermined

STEPS = ("register", "gain", "mae", "warp", "verdict")
#: Trailing shape of the per-position vectors of :meth:`GridCharacterization.table`.
VECTOR_SHAPES = {"shift": (2,), "field_deg": (2,), "monitor_px": (2,)}
QUIVER_CELLS = 24        # arrows along the longest side of a stored residual flow


@dataclass(frozen=True)
class CharacterizeOptions:
    """Options of :func:`psfkit.characterization.characterize.characterize_grid`.

    Attributes
    ----------
    steps : tuple of str
        Subset of :data:`STEPS` (registration always runs; ``"verdict"``: the held-out
        cross-validation of :mod:`psfkit.fitting.verdict` on a binned working copy).
    upsample : int
        Registration precision ``1/upsample`` px.
    flow_method : str
        Dense-flow method of the warp residual.
    per_channel : bool
        Also register every colour channel on its own (lateral colour).
    mae_smoothing_px : float
        Gaussian σ (px) on both PSFs before the MAE (0: raw pixels).
    min_quality : float
        Lowest registration NCC of a kept position.
    strict : bool
        A failed quality check ends the run instead of excluding the position.
    """

    preprocess: PreprocessOptions = field(default_factory=PreprocessOptions)
    steps: tuple[str, ...] = STEPS
    upsample: int = 100
    flow_method: str = "dis"
    per_channel: bool = False
    mae_smoothing_px: float = 1.0
    min_quality: float = MIN_QUALITY
    strict: bool = False

    def __post_init__(self) -> None:
        unknown = set(self.steps) - set(STEPS)
        if unknown:
            raise ConfigurationError(f"unknown step(s) {sorted(unknown)}; choose from {STEPS}")
        if self.flow_method not in FLOW_METHODS:
            raise ConfigurationError(f"flow_method must be one of {FLOW_METHODS}")
        if self.upsample < 1:
            raise ConfigurationError("upsample must be >= 1")
        if self.mae_smoothing_px < 0:
            raise ConfigurationError("mae_smoothing_px must be >= 0")
        if not 0 <= self.min_quality <= 1:
            raise ConfigurationError(f"--min-ncc must be in [0, 1], got {self.min_quality}")


@dataclass
class PositionResult:
    """Measurements at one grid position (NaN where a step did not run)."""

    row: int
    col: int
    file: str
    field_deg: tuple[float, float] | None
    monitor_px: tuple[float, float] | None
    shift: tuple[float, float]
    quality: float
    overlap: float
    n_saturated: int
    saturated_fraction: float
    snr: float
    support_overlap: float = float("nan")
    channel_shifts: list[tuple[float, float]] | None = None
    gain: float = float("nan")
    mae: float = float("nan")
    mae_gain_compensated: float = float("nan")
    warp: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        out["shift_px"] = list(out.pop("shift"))
        return out


@dataclass
class GridCharacterization:
    """Everything ``characterize_grid`` measured, plus images for the figures: ``positions``
    measured, ``excluded`` (with reasons), ``missing`` lattice cells. Tables (:meth:`table`) are
    ``(N, M)`` (``(1, P)`` for an irregular scan), NaN where not measured.
    """

    grid_root: str
    grid_shape: tuple[int, int]
    image_shape: tuple[int, int, int]
    channels: tuple[str, ...]
    center: tuple[int, int]
    options: CharacterizeOptions
    positions: list[PositionResult]
    field_units: str
    shift_fit: ShiftMapFit | None = None
    gain_fit: GainFit | None = None
    warp_growth: GrowthFit | None = None
    warp_anisotropy: dict[str, float] | None = None
    reference: np.ndarray | None = field(default=None, repr=False)
    examples: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, repr=False)   # (aligned image, valid mask) for Fig. 2
    # (N, M, h, w) luminance windows around each PSF for the montage: the reference's support
    # box (psf_box, full-resolution px) moved by the position's shift, binned to <= 160 px
    thumbnails: np.ndarray | None = field(default=None, repr=False)
    psf_box: tuple[slice, slice] | None = field(default=None, repr=False)
    flows: dict[tuple[int, int], np.ndarray] = field(default_factory=dict, repr=False)
    layout: str = FULL_LATTICE
    excluded: list[ExcludedPosition] = field(default_factory=list)
    missing: list[tuple[int, int]] = field(default_factory=list)
    astigmatism: Estimate | None = None     # tangential/sagittal ratio (warp step)
    verdict: Verdict | None = None          # the verdict step

    def effects(self) -> dict[str, Estimate]:
        """The measured field effects of the verdict (:data:`psfkit.fitting.verdict.EFFECTS`):
        shift distortion, cosⁿ exponent, warp growth, tangential/sagittal ratio."""
        out: dict[str, Estimate] = {}
        if self.shift_fit is not None:
            out["shift"] = self.shift_fit.distortion
        if self.gain_fit is not None:
            out["gain"] = self.gain_fit.estimate
        if "warp" in self.options.steps:
            out["warp"] = self.warp_growth.growth if self.warp_growth is not None else \
                undetermined("fewer than four positions with a measured warp residual")
            out["astigmatism"] = self.astigmatism if self.astigmatism is not None else \
                undetermined("no position with a measured anisotropy far enough off axis",
                             null=1.0)
        return out

    def _lattice(self, items: list[Any], values: list[Any], extra: tuple[int, ...] = ()
                 ) -> np.ndarray:
        """``values`` of ``items`` on the ``(N, M, *extra)`` lattice (NaN elsewhere); ``extra``
        is the values' shape, or the one given when there are none."""
        n, m = self.grid_shape
        extra = np.shape(values[0]) if values else extra
        out = np.full((n, m, *extra), np.nan)
        for item, value in zip(items, values, strict=True):
            out[item.row, item.col] = value
        return out

    def table(self, key: str) -> np.ndarray:
        """``(N, M)`` (or ``(N, M, k)``) array of a per-position quantity."""
        return self._lattice(self.positions, [getattr(p, key) for p in self.positions],
                             VECTOR_SHAPES.get(key, ()))

    def warp_table(self, key: str) -> np.ndarray:
        """``(N, M)`` array of a warp statistic (NaN where no warp was measured)."""
        return self._lattice(self.positions, [p.warp[key] if p.warp else np.nan
                                              for p in self.positions])

    @property
    def captured(self) -> list[PositionResult | ExcludedPosition]:
        """Measured and excluded positions (every position of the manifest)."""
        return [*self.positions, *self.excluded]

    def status(self) -> np.ndarray:
        """``(N, M)`` str array: ``"ok"``, ``"excluded"`` or ``"missing"``."""
        out = np.full(self.grid_shape, "missing", dtype=object)
        for p in self.positions:
            out[p.row, p.col] = "ok"
        for e in self.excluded:
            out[e.row, e.col] = "excluded"
        return out

    def field_coordinates(self) -> np.ndarray:
        """``(N, M, 2)`` field positions in :attr:`field_units` (NaN where not captured)."""
        n, m = self.grid_shape
        items = self.captured
        if self.field_units == "monitor px":
            return self._lattice(items, [p.monitor_px for p in items])
        if self.field_units == "tan(field angle)":
            return np.tan(np.deg2rad(self._lattice(items, [p.field_deg for p in items])))
        rows, cols = np.mgrid[0:n, 0:m]
        return np.stack([cols - self.center[1], rows - self.center[0]], axis=-1).astype(float)

    def field_angle_deg(self) -> np.ndarray | None:
        """``(N, M)`` total field angle θ, or ``None`` without field angles."""
        items = self.captured
        if any(p.field_deg is None for p in items):
            return None
        t = np.tan(np.deg2rad(self._lattice(items, [p.field_deg for p in items])))
        return np.rad2deg(np.arctan(np.hypot(t[..., 0], t[..., 1])))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary and per-position numbers."""
        opts = self.options
        return {
            "grid": self.grid_root, "grid_shape": list(self.grid_shape),
            "image_shape": list(self.image_shape), "channels": list(self.channels),
            "center": list(self.center),
            "conventions": {
                "shift": "(du, dv) displacement of each PSF relative to the centre PSF, sensor "
                         "px; u = column, v = row; a source at +x gives du < 0",
                "normalization": f"PSFs divided by the centre PSF's {opts.preprocess.normalization}"
                                 " (all channels), so gains are relative to the centre",
                "mae": "Σ|PSF − centre| / Σ centre (energy-normalised, so independent of the "
                       "frame size) over the PSFs' support (where either, smoothed by 1 px, "
                       "exceeds 1% of its peak and 6× its noise, grown by 3 px) inside the "
                       "registered overlap, all channels, saturated pixels excluded, after a "
                       f"Gaussian of σ = {opts.mae_smoothing_px:g} px on both",
                "support_overlap": "fraction of the centre PSF's light (over its support) "
                                   "inside a position's registered overlap; a position is "
                                   "reliable when it is at least reliable_overlap",
                "gain": "Σ PSF / Σ centre over the PSFs' support inside the registered overlap "
                        "(a compact PSF), or over the whole overlap (a PSF whose support covers "
                        "≥ 20 % of the sensor): includes any difference in source brightness, "
                        "not only vignetting",
                "quality": "NCC of the luminances over the PSFs' support inside the registered "
                           "overlap",
                "uncertainty": "every fitted field quantity is under 'estimates': value, 1σ "
                               "(sigma), null, z, p_value of its test, significant "
                               f"(|value − null| > {Z_SIGNIFICANT:g}σ and p < "
                               f"{alpha():.2g}), status",
                "warp": "moving(x + d(x)) ≈ centre(x); affine part by ECC about the image "
                        "centre, residual by dense flow; tangential = along the PSF shift",
            },
            "options": {"steps": list(opts.steps), "upsample": opts.upsample,
                        "flow_method": opts.flow_method, "per_channel": opts.per_channel,
                        "mae_smoothing_px": opts.mae_smoothing_px,
                        "preprocess": dict(opts.preprocess.__dict__)},
            "field_units": self.field_units,
            "shift_map": self.shift_fit.to_dict() if self.shift_fit else None,
            "gain_fit": self.gain_fit.to_dict() if self.gain_fit else None,
            "warp_growth": self.warp_growth.to_dict() if self.warp_growth else None,
            "warp_anisotropy": self.warp_anisotropy,
            **({"verdict": self.verdict.to_dict()} if self.verdict is not None else {}),
            "reliable_overlap": RELIABLE_OVERLAP,
            "positions": [p.to_dict() for p in self.positions],
            **self.coverage(),
        }

    def coverage(self) -> dict[str, Any]:
        """Layout, missing cells and excluded positions with reasons (empty for a complete
        full lattice at the default NCC threshold)."""
        complete = self.layout == FULL_LATTICE and not self.excluded
        if complete and self.options.min_quality == MIN_QUALITY:
            return {}
        return {"layout": self.layout,
                "positions_measured": len(self.positions),
                "missing": [list(index) for index in self.missing],
                "excluded": [e.to_dict() for e in self.excluded],
                "exclusion_reasons": {r: REJECTION_REASONS[r]
                                      for r in sorted({e.reason for e in self.excluded})},
                "min_quality": self.options.min_quality}
