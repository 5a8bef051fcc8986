"""One pass over a PSF grid: registration, gain, MAE and warp against the centre PSF.

``characterize_grid`` reads one PSF at a time (a full-resolution 9 × 9 RGB grid never sits in
memory), preprocesses it (:mod:`psfkit.preprocess`), registers it to the centre PSF
(:mod:`psfkit.registration`), aligns it, and measures what each requested step needs. The
result keeps the per-position numbers plus small images for the figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from psfkit.alignment import (
    MIN_QUALITY,
    REJECTION_REASONS,
    RELIABLE_OVERLAP,
    AlignedPsf,
    ExcludedPosition,
    GridAligner,
    nominal_shifts,
)
from psfkit.choices import CV_BASES_ALL
from psfkit.eigen import WorkingStack, working_region
from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.gain import GainFit, fit_gain, overlap_gain
from psfkit.heldout import VERDICT_WORKING_SIZE, judge, moved_to
from psfkit.io.grid import FULL_LATTICE, IRREGULAR, GridPosition, PsfGrid
from psfkit.mae import mean_absolute_error
from psfkit.parallel import bounded_map
from psfkit.preprocess import PreprocessOptions
from psfkit.registration import (
    ShiftMapFit,
    fit_shift_map,
)
from psfkit.resample import bin_image, binning_factor
from psfkit.significance import (
    Z_SIGNIFICANT,
    Estimate,
    alpha,
    checked,
    t_test,
    undetermined,
)
from psfkit.support import crop_window, support_box
from psfkit.verdict import Verdict
from psfkit.warp import (
    FLOW_METHODS,
    GrowthFit,
    fit_growth,
    geometric_anisotropy,
    split_rms,
    transport_anisotropy,
    warp_field,
)

STEPS = ("register", "gain", "mae", "warp", "verdict")
#: Trailing shape of the per-position vectors of :meth:`GridCharacterization.table`.
VECTOR_SHAPES = {"shift": (2,), "field_deg": (2,), "monitor_px": (2,)}
THUMBNAIL_SIZE = 160     # longest side of montage thumbnails, px
QUIVER_CELLS = 24        # arrows along the longest side of a stored residual flow


@dataclass(frozen=True)
class CharacterizeOptions:
    """Options of :func:`characterize_grid`.

    Attributes
    ----------
    preprocess : PreprocessOptions
    steps : tuple of str
        Subset of ``("register", "gain", "mae", "warp", "verdict")`` (registration always
        runs; ``"verdict"``: the held-out cross-validation over positions and the verdict of
        :mod:`psfkit.verdict`, on a binned working copy of the aligned PSFs).
    upsample : int
        Registration precision is ``1/upsample`` px.
    flow_method : str
        Dense-flow method of the warp residual (``"dis"``, ``"farneback"``, ``"ilk"``,
        ``"tvl1"``).
    per_channel : bool
        Also register every colour channel on its own (lateral colour).
    mae_smoothing_px : float
        Gaussian σ (px) applied to both PSFs before the MAE, so that sensor noise does not
        swamp the model error near the axis (0: raw pixels).
    min_quality : float
        Positions whose registration quality (NCC) is below this are excluded ("low NCC").
    strict : bool
        All or nothing: a position that fails a quality check ends the run (as before
        issue 26) instead of being excluded with its reason.
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
        out = {k: v for k, v in self.__dict__.items()}
        out["shift_px"] = list(out.pop("shift"))
        return out


@dataclass
class GridCharacterization:
    """Everything :func:`characterize_grid` measured, plus images for the figures.

    ``positions`` holds the measured positions; ``excluded`` the captured ones left out, with
    their reasons; ``missing`` the cells of the declared lattice that were never captured.
    Per-position tables (:meth:`table`) are ``(N, M)`` lattices (``(1, P)`` for an irregular
    scan) with NaN in the cells of excluded and missing positions.
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
        """The field effects of the verdict (:data:`psfkit.verdict.EFFECTS`) that were
        measured: shift = the shift map's non-linear part, gain = the cosⁿ exponent, warp =
        the growth of the warp residual, astigmatism = the tangential/sagittal ratio."""
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
        """``values`` of ``items`` on the ``(N, M, *extra)`` lattice (NaN elsewhere); the
        trailing shape ``extra`` is that of the values, or the one given when there are none
        (a vector quantity keeps its axis when no position was measured)."""
        n, m = self.grid_shape
        extra = np.shape(values[0]) if values else extra
        out = np.full((n, m, *extra), np.nan)
        for item, value in zip(items, values, strict=True):
            out[item.row, item.col] = value
        return out

    def table(self, key: str) -> np.ndarray:
        """``(N, M)`` (or ``(N, M, k)``) array of a per-position quantity (NaN where not
        measured)."""
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
        """``(N, M)`` total field angle θ (NaN where not captured), or ``None`` without field
        angles."""
        items = self.captured
        if any(p.field_deg is None for p in items):
            return None
        t = np.tan(np.deg2rad(self._lattice(items, [p.field_deg for p in items])))
        return np.rad2deg(np.arctan(np.hypot(t[..., 0], t[..., 1])))

    @property
    def is_complete(self) -> bool:
        """A full lattice with every position measured (the pre-issue-26 case)."""
        return self.layout == FULL_LATTICE and not self.excluded

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
        """The layout, the cells never captured and the excluded positions with their
        reasons; empty for a complete full lattice (its documents stay as before issue 26)."""
        if self.is_complete and self.options.min_quality == MIN_QUALITY:
            return {}
        return {"layout": self.layout,
                "positions_measured": len(self.positions),
                "missing": [list(index) for index in self.missing],
                "excluded": [e.to_dict() for e in self.excluded],
                "exclusion_reasons": {r: REJECTION_REASONS[r]
                                      for r in sorted({e.reason for e in self.excluded})},
                "min_quality": self.options.min_quality}


def _field_units(grid: PsfGrid) -> str:
    if grid.monitor_px() is not None:
        return "monitor px"
    if grid.field_deg() is not None:
        return "tan(field angle)"
    return "grid steps"


def _fig2_positions(grid: PsfGrid, center: tuple[int, int]) -> list[tuple[int, int]]:
    """Off-axis positions B and C of Fig. 2: halfway to the farther edge and at that edge,
    along the vertical through the centre as in the paper (horizontal for a one-row grid);
    of an irregular scan, the position farthest from the centre and the one nearest halfway
    to it."""
    if grid.is_irregular:
        coords = grid.monitor_px() if grid.monitor_px() is not None else grid.field_deg()
        assert coords is not None
        radius = np.hypot(*np.moveaxis(coords[0] - coords[center], -1, 0))
        far = int(np.argmax(radius))
        half = int(np.argmin(np.where(radius > 0, np.abs(radius - radius[far] / 2), np.inf)))
        return list(dict.fromkeys([(0, half), (0, far)]))
    n, m = grid.grid_shape
    r0, c0 = center
    if n > 1:
        far = 0 if r0 >= n - 1 - r0 else n - 1
        return [((r0 + far) // 2, c0), (far, c0)]
    far = 0 if c0 >= m - 1 - c0 else m - 1
    return [(r0, (c0 + far) // 2), (r0, far)]


def _smooth(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of every channel of a ``(C, H, W)`` image (identity for σ = 0)."""
    if sigma <= 0:
        return image
    return np.stack([cv2.GaussianBlur(channel, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
                     for channel in image])


def _thumbnail(image: np.ndarray) -> np.ndarray:
    factor = binning_factor(image.shape, THUMBNAIL_SIZE)
    return bin_image(image, factor) / factor**2


def _coarse_flow(flow: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Block-average a ``(2, H, W)`` flow over the masked pixels to ``(3, h, w)``:
    ``(d_u, d_v, fraction of masked pixels)`` for quiver plots."""
    factor = binning_factor(flow.shape[1:], QUIVER_CELLS)
    weight = bin_image(mask.astype(np.float64), factor)
    du = bin_image(np.where(mask, flow[0], 0.0), factor) / np.maximum(weight, 1)
    dv = bin_image(np.where(mask, flow[1], 0.0), factor) / np.maximum(weight, 1)
    return np.stack([du, dv, weight / factor**2]).astype(np.float32)


def characterize_grid(grid: PsfGrid, options: CharacterizeOptions | None = None,
                      progress: bool = False, workers: int | None = None
                      ) -> GridCharacterization:
    """Register every PSF of ``grid`` to its centre PSF and measure gain, MAE and warp.

    Parameters
    ----------
    grid : PsfGrid
        From :func:`psfkit.io.read_grid`.
    options : CharacterizeOptions
    progress : bool
        Show a progress bar.
    workers : int, optional
        Positions processed concurrently (default: 2, or 1 on a single core).

    Raises
    ------
    GridFormatError
        The grid has no centre position.
    InvalidInputError
        A PSF is empty, too saturated, or does not overlap the centre PSF (message names the
        file).
    """
    options = options or CharacterizeOptions()
    aligner = GridAligner(grid, options.preprocess, options.upsample,
                          min_quality=options.min_quality, strict=options.strict)
    center = aligner.center
    ref_lum = aligner.reference_luminance
    steps = set(options.steps)
    working = _WorkingCopy(grid, aligner, enabled="verdict" in steps)
    fig2 = set(_fig2_positions(grid, center))
    box = support_box(ref_lum)      # the figures show the PSF, not the frame
    thumbnails = np.zeros((*grid.grid_shape, *_thumbnail(crop_window(ref_lum, box)).shape),
                          np.float32)

    result = GridCharacterization(
        grid_root=str(grid.root), grid_shape=grid.grid_shape, image_shape=grid.image_shape,
        channels=grid.channels, center=center, options=options, positions=[],
        field_units=_field_units(grid), reference=aligner.reference, layout=grid.layout,
        missing=grid.missing(), psf_box=box)

    measure = _PositionMeasurement(grid, options, aligner, steps, working, fig2, box)

    records: list[PositionResult | ExcludedPosition | None] = [None] * len(grid.positions)
    bar: Any = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(grid.positions), desc="characterizing PSFs", unit="psf")

    def collect(index: int, record: PositionResult | ExcludedPosition,
                extras: dict[str, Any]) -> None:
        records[index] = record
        if bar is not None:
            bar.update()
        if isinstance(record, ExcludedPosition):
            return
        here = (record.row, record.col)
        thumbnails[here] = extras["thumbnail"]
        if "example" in extras:
            result.examples[here] = extras["example"]
        if "flow" in extras:
            result.flows[here] = extras["flow"]

    try:
        for index, (record, extras) in bounded_map(measure, grid.positions, workers):
            collect(index, record, extras)
    finally:
        if bar is not None:
            bar.close()
    result.positions = [r for r in records if isinstance(r, PositionResult)]
    result.excluded = [r for r in records if isinstance(r, ExcludedPosition)]

    result.thumbnails = thumbnails
    coords = result.field_coordinates()
    overlaps = result.table("support_overlap")
    result.shift_fit = _shift_map(result, grid, coords, overlaps, options.upsample)
    if "gain" in steps:
        result.gain_fit = fit_gain(result.table("gain"), grid.field_deg(), coords,
                                   weights=overlaps)
    if "warp" in steps:
        _summarise_warp(result)
    result.verdict = working.verdict(grid, result, records, progress)
    return result


class _PositionMeasurement:
    """Align one position of the grid to its centre PSF and measure it: its
    :class:`PositionResult` (or why it is excluded) and what the figures keep of it
    (``thumbnail``; ``example`` at the Fig. 2 positions; ``flow`` where a warp was measured).
    Called concurrently on the positions (:func:`~psfkit.parallel.bounded_map`)."""

    def __init__(self, grid: PsfGrid, options: CharacterizeOptions, aligner: GridAligner,
                 steps: set[str], working: _WorkingCopy, fig2: set[tuple[int, int]],
                 box: Any) -> None:
        self.grid, self.options, self.aligner, self.steps = grid, options, aligner, steps
        self.working, self.fig2, self.box = working, fig2, box
        self.ref_total = aligner.reference.sum(axis=0)
        self.ref_smooth = _smooth(aligner.reference, options.mae_smoothing_px)

    def __call__(self, pos: GridPosition
                 ) -> tuple[PositionResult | ExcludedPosition, dict[str, Any]]:
        aligner, options, steps = self.aligner, self.options, self.steps
        here = (pos.row, pos.col)
        item = aligner.try_align(pos)
        if isinstance(item, ExcludedPosition):
            return item, {}
        aligned, valid, shift, prep = item.image, item.valid, item.shift, item.prepared
        window = crop_window(prep.luminance / np.float32(aligner.scale), self.box,
                             (round(shift[1]), round(shift[0])))
        extras: dict[str, Any] = {"thumbnail": _thumbnail(window)}
        record = PositionResult(
            row=pos.row, col=pos.col, file=pos.file, field_deg=pos.field_deg,
            monitor_px=pos.monitor_px, shift=shift,
            quality=item.quality, overlap=item.overlap,
            n_saturated=prep.n_saturated, saturated_fraction=prep.saturated_fraction,
            snr=prep.snr, support_overlap=item.support_overlap)
        if options.per_channel and aligned.shape[0] > 1:
            record.channel_shifts = self._channel_shifts(here, prep.image)
        gain = overlap_gain(self.ref_total, aligned.sum(axis=0), aligner.gain_region(item))
        self.working.put(item, aligned, gain)
        if "gain" in steps:
            record.gain = gain
        if "mae" in steps:
            self._mae(record, aligned, item.compared, gain)
        if here in self.fig2:
            extras["example"] = (aligned, valid)
        if "warp" in steps and here != aligner.center:
            measured = _try_warp(aligner.reference_luminance, item.luminance / np.float32(gain),
                                 valid, shift, options.flow_method, str(self.grid.path(*here)))
            if measured is not None:
                record.warp, extras["flow"] = measured
        return record, extras

    def _channel_shifts(self, here: tuple[int, int], image: np.ndarray
                        ) -> list[tuple[float, float]]:
        """The shift of each colour channel against the centre PSF's same channel."""
        aligner = self.aligner
        image = image / np.float32(aligner.scale)
        return [(0.0, 0.0) if here == aligner.center
                else aligner.register(aligner.reference[c], image[c])
                for c in range(image.shape[0])]

    def _mae(self, record: PositionResult, aligned: np.ndarray, compared: np.ndarray,
             gain: float) -> None:
        # compared over the PSFs' support inside the overlap: frame-size independent (the
        # noise of a large frame's empty pixels would otherwise dominate a compact PSF)
        al_smooth = _smooth(aligned, self.options.mae_smoothing_px)
        record.mae = mean_absolute_error(self.ref_smooth, al_smooth, compared)
        record.mae_gain_compensated = mean_absolute_error(self.ref_smooth, al_smooth, compared,
                                                          gain)


def _try_warp(ref_lum: np.ndarray, lum: np.ndarray, valid: np.ndarray,
              shift: tuple[float, float], method: str, where: str
              ) -> tuple[dict[str, Any], Any] | None:
    """One position's warp statistics and coarse flow (:func:`_warp_position`), or ``None``
    when too few PSF pixels overlap for a dense flow (a compact PSF at the sensor's edge): no
    warp at this position, not the end of the report."""
    try:
        warp, (residual, mask) = _warp_position(ref_lum, lum, valid, shift, method, where)
    except InvalidInputError:
        return None
    return warp, _coarse_flow(residual, mask)


def _shift_map(result: GridCharacterization, grid: PsfGrid, coords: np.ndarray,
               weights: np.ndarray, upsample: int) -> ShiftMapFit | None:
    """The field → shift map over the measured positions; ``None`` for a one-row lattice or
    positions that do not span two directions."""
    if grid.layout != IRREGULAR and min(grid.grid_shape) == 1:
        return None
    try:
        return fit_shift_map(coords, result.table("shift"), result.field_units,
                             weights=weights, resolution_px=1.0 / upsample)
    except InvalidInputError:
        return None


class _WorkingCopy:
    """The working copy of the aligned PSFs the verdict is judged on (nothing when not
    ``enabled``), chosen from the centre PSF's extent as ``psfkit fit-eigen`` chooses its own
    (:func:`psfkit.eigen.working_region`); one row per position of the grid, so that the
    worker threads never write the same one."""

    def __init__(self, grid: PsfGrid, aligner: GridAligner, enabled: bool) -> None:
        self.stack = None
        if enabled:
            region, factor, _ = working_region(aligner.reference_support,
                                               aligner.reference_luminance,
                                               VERDICT_WORKING_SIZE)
            self.stack = WorkingStack.empty(len(grid.positions), grid.image_shape, factor,
                                            region)
        self.rows = {(pos.row, pos.col): i for i, pos in enumerate(grid.positions)}

    def put(self, item: AlignedPsf, image: np.ndarray, gain: float) -> None:
        if self.stack is not None:
            self.stack.put(self.rows[(item.position.row, item.position.col)], item, image,
                           gain)

    def verdict(self, grid: PsfGrid, result: GridCharacterization, records: list[Any],
                progress: bool) -> Verdict | None:
        """:func:`judge_grid` on the measured positions (``None`` when not enabled)."""
        if self.stack is None:
            return None
        kept = np.array([isinstance(r, PositionResult) for r in records])
        return judge_grid(grid, result, self.stack.subset(kept), progress)


def judge_grid(grid: PsfGrid, result: GridCharacterization, stack: WorkingStack,
               progress: bool = False) -> Verdict:
    """The verdict of a characterized grid (:mod:`psfkit.heldout`) from the working copy of
    its aligned PSFs and the field effects measured. The PSFs are placed as ``psfkit
    fit-eigen`` places them (:func:`psfkit.alignment.nominal_shifts`: the forward model's
    affine map of the field), so that both commands judge the same data."""
    positions = [grid.position(p.row, p.col) for p in result.positions]
    placement = nominal_shifts(positions, np.array([p.shift for p in result.positions]),
                               np.array([p.support_overlap if math.isfinite(p.support_overlap)
                                         else p.overlap for p in result.positions]),
                               result.center)
    stack = moved_to(stack, np.array([placement.shifts[(p.row, p.col)] for p in positions]))
    _, verdict = judge(stack, stack.row_of(result.center), result.image_shape[1:],
                       list(CV_BASES_ALL), effects=result.effects(), progress=progress)
    return verdict


def _summarise_warp(result: GridCharacterization) -> None:
    """Grid-level warp summary over the positions mostly on the sensor: growth of the residual
    with field angle, and the tangential/sagittal anisotropy against geometric optics."""
    theta = result.field_angle_deg()
    if theta is None:
        return
    reliable = result.table("support_overlap") >= RELIABLE_OVERLAP
    residual = np.where(reliable, result.warp_table("residual_rms"), np.nan)
    result.warp_growth = fit_growth(theta, residual)
    anisotropy = result.warp_table("anisotropy")
    # far enough off axis for the astigmatic displacement to dominate the flow's error floor
    strong = reliable & np.isfinite(anisotropy) & (anisotropy > 0) \
        & (theta >= 0.4 * np.nanmax(theta))
    if strong.any():
        ratio = anisotropy[strong] / geometric_anisotropy(theta[strong])
        result.warp_anisotropy = {
            "positions": int(strong.sum()),
            "median_measured": float(np.median(anisotropy[strong])),
            "median_geometric": float(np.median(geometric_anisotropy(theta[strong]))),
            "median_ratio_to_geometric": float(np.median(ratio)),
            "fraction_tangential": float(np.mean(anisotropy[strong] > 1.0)),
        }
        result.astigmatism = astigmatism_estimate(anisotropy[strong])
        result.warp_anisotropy["estimates"] = {
            "tangential_sagittal": result.astigmatism.to_dict()}


def astigmatism_estimate(anisotropy: np.ndarray) -> Estimate:
    """The tangential/sagittal ratio of the warp residual over the positions, as an
    :class:`~psfkit.significance.Estimate`: the geometric mean of the per-position ratios
    (finite, positive) with its 1σ from their scatter (delta method on the mean of their
    logarithms), against the null 1 (no astigmatism: an isotropic change), tested by the
    one-sample t-test of the logarithms."""
    ratios = np.asarray(anisotropy, dtype=np.float64).ravel()
    ratios = ratios[np.isfinite(ratios) & (ratios > 0)]
    if len(ratios) < 3:
        return undetermined(f"{len(ratios)} position(s) with a measured anisotropy far enough "
                            "off axis; the test needs at least 3", null=1.0)
    logs = np.log(ratios)
    mean, sem = float(np.mean(logs)), float(np.std(logs, ddof=1) / np.sqrt(len(logs)))
    p_value = t_test(mean, sem, len(logs) - 1) if sem > 0 else 0.0
    value = math.exp(mean)
    return checked(value, value * sem if sem > 0 else 1e-12 * value, 1.0, p_value)


def _warp_position(ref_lum: np.ndarray, al_lum: np.ndarray, valid: np.ndarray,
                   shift: tuple[float, float], method: str, where: str = "PSF"
                   ) -> tuple[dict[str, Any], tuple[np.ndarray, np.ndarray]]:
    """Warp statistics of one position, plus ``(residual flow, mask)`` for the figures
    (``where`` names the position's file in an error)."""
    try:
        warp = warp_field(ref_lum, al_lum, valid, method)
    except InvalidInputError as exc:
        raise InvalidInputError(f"{where}: {exc}") from None
    # tangential = direction of the PSF's shift (radial on the sensor)
    azimuth = float(np.arctan2(shift[1], shift[0]))
    m = warp.mask
    residual_rms = float(np.sqrt(np.mean(np.sum(warp.residual[:, m] ** 2, axis=0))))
    anisotropy = transport_anisotropy(ref_lum, warp.compensated, m, azimuth)
    rms_t, rms_s = split_rms(residual_rms, anisotropy)
    stats = {
        "affine": warp.affine.to_dict(azimuth), "ecc": warp.ecc,
        "azimuth_deg": float(np.degrees(azimuth)),
        "residual_rms": residual_rms, "anisotropy": anisotropy,
        "rms_tangential": rms_t, "rms_sagittal": rms_s,
        "mask_fraction": float(m.mean()),
    }
    return stats, (warp.residual, m)
