"""One pass over a PSF grid, one PSF at a time (a full-resolution grid never sits in memory):
preprocess, register and align each PSF to the centre PSF and measure gain, MAE and warp; the
result keeps the per-position numbers and small images for the figures.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any

import cv2
import numpy as np

from psfkit.calibration.alignment import (
    RELIABLE_OVERLAP,
    ExcludedPosition,
    GridAligner,
)
from psfkit.calibration.gain import fit_gain, overlap_gain
from psfkit.calibration.mae import mean_absolute_error
from psfkit.calibration.nominal_shifts import field_units, nominal_shifts
from psfkit.calibration.shift_map import ShiftMapFit, fit_shift_map
from psfkit.calibration.support import crop_window, support_box
from psfkit.calibration.warp import (
    fit_growth,
    geometric_anisotropy,
    split_rms,
    transport_anisotropy,
    warp_field,
)
from psfkit.characterization.results import (
    QUIVER_CELLS,
    CharacterizeOptions,
    GridCharacterization,
    PositionResult,
)
from psfkit.choices import CV_BASES_ALL
from psfkit.errors import InvalidInputError
from psfkit.fitting.grid.heldout import VERDICT_WORKING_SIZE, judge, moved_to
from psfkit.fitting.grid.working_stack import WorkingStack, working_region
from psfkit.fitting.verdict import Verdict
from psfkit.io.grid import IRREGULAR, GridPosition, PsfGrid
from psfkit.numerics.parallel import bounded_map
from psfkit.numerics.resample import bin_image, binning_factor
from psfkit.numerics.significance import Estimate, checked, t_test, undetermined

THUMBNAIL_SIZE = 160     # longest side of montage thumbnails, px


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
    """``(3, h, w)`` ``(d_u, d_v, masked fraction)``: a ``(2, H, W)`` flow's block averages."""
    factor = binning_factor(flow.shape[1:], QUIVER_CELLS)
    weight = bin_image(mask.astype(np.float64), factor)
    mean = bin_image(np.where(mask, flow, 0.0), factor) / np.maximum(weight, 1)
    return np.concatenate([mean, (weight / factor**2)[None]]).astype(np.float32)


def characterize_grid(grid: PsfGrid, options: CharacterizeOptions | None = None,
                      progress: bool = False, workers: int | None = None
                      ) -> GridCharacterization:
    """Register every PSF of ``grid`` to its centre PSF and measure gain, MAE and warp.

    ``workers``: positions processed concurrently (default: 2, or 1 on a single core).

    Raises
    ------
    GridFormatError
        The grid has no centre position.
    InvalidInputError
        An unusable centre PSF (or, with ``strict``, any PSF), naming the file.
    """
    options = options or CharacterizeOptions()
    aligner = GridAligner(grid, options.preprocess, options.upsample,
                          min_quality=options.min_quality, strict=options.strict)
    center = aligner.center
    ref_lum = aligner.reference_luminance
    steps = set(options.steps)
    stack = None    # the working copy the verdict is judged on, chosen as fit-eigen does
    if "verdict" in steps:
        region, factor, _ = working_region(aligner.reference_support, ref_lum,
                                           VERDICT_WORKING_SIZE)
        stack = WorkingStack.empty(len(grid.positions), grid.image_shape, factor, region)
    fig2 = set(_fig2_positions(grid, center))
    box = support_box(ref_lum)      # the figures show the PSF, not the frame
    thumbnails = np.zeros((*grid.grid_shape, *_thumbnail(crop_window(ref_lum, box)).shape),
                          np.float32)

    result = GridCharacterization(
        grid_root=str(grid.root), grid_shape=grid.grid_shape, image_shape=grid.image_shape,
        channels=grid.channels, center=center, options=options, positions=[],
        field_units=field_units(grid.positions), reference=aligner.reference, layout=grid.layout,
        missing=grid.missing(), psf_box=box)

    measure = _PositionMeasurement(grid, options, aligner, steps, stack, fig2, box)

    records: list[PositionResult | ExcludedPosition | None] = [None] * len(grid.positions)
    bar: Any = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(grid.positions), desc="characterizing PSFs", unit="psf")

    try:
        for index, (record, extras) in bounded_map(measure, grid.positions, workers):
            records[index] = record
            if bar is not None:
                bar.update()
            if isinstance(record, ExcludedPosition):
                continue
            here = (record.row, record.col)
            thumbnails[here] = extras["thumbnail"]
            if "example" in extras:
                result.examples[here] = extras["example"]
            if "flow" in extras:
                result.flows[here] = extras["flow"]
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
    if stack is not None:
        kept = np.array([isinstance(r, PositionResult) for r in records])
        result.verdict = judge_grid(grid, result, stack.subset(kept), progress)
    return result


class _PositionMeasurement:
    """Align one position to the centre PSF and measure it (called concurrently): its
    :class:`PositionResult` or exclusion, and what the figures keep (``thumbnail``,
    ``example`` at the Fig. 2 positions, ``flow``)."""

    def __init__(self, grid: PsfGrid, options: CharacterizeOptions, aligner: GridAligner,
                 steps: set[str], stack: WorkingStack | None, fig2: set[tuple[int, int]],
                 box: Any) -> None:
        self.grid, self.options, self.aligner, self.steps = grid, options, aligner, steps
        self.stack, self.fig2, self.box = stack, fig2, box
        # one stack row per position, so threads never share one
        self.rows = {(p.row, p.col): i for i, p in enumerate(grid.positions)}
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
        if self.stack is not None:
            self.stack.put(self.rows[here], item, aligned, gain)
        if "gain" in steps:
            record.gain = gain
        if "mae" in steps:
            self._mae(record, aligned, item.compared, gain)
        if here in self.fig2:
            extras["example"] = (aligned, valid)
        if "warp" in steps and here != aligner.center:
            # too few PSF pixels overlapping for a dense flow: no warp there, the report goes on
            with contextlib.suppress(InvalidInputError):
                record.warp, (residual, mask) = _warp_position(
                    aligner.reference_luminance, item.luminance / np.float32(gain), valid, shift,
                    options.flow_method, str(self.grid.path(*here)))
                extras["flow"] = _coarse_flow(residual, mask)
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


def _shift_map(result: GridCharacterization, grid: PsfGrid, coords: np.ndarray,
               weights: np.ndarray, upsample: int) -> ShiftMapFit | None:
    """The field → shift map; ``None`` for positions that do not span two directions."""
    if grid.layout != IRREGULAR and min(grid.grid_shape) == 1:
        return None
    try:
        return fit_shift_map(coords, result.table("shift"), result.field_units,
                             weights=weights, resolution_px=1.0 / upsample)
    except InvalidInputError:
        return None


def judge_grid(grid: PsfGrid, result: GridCharacterization, stack: WorkingStack,
               progress: bool = False) -> Verdict:
    """The verdict (:mod:`psfkit.fitting.grid.heldout`) of a characterized grid from the working
    copy of its aligned PSFs, placed by
    :func:`~psfkit.calibration.nominal_shifts.nominal_shifts` as ``psfkit fit-eigen`` does."""
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
    """Warp growth and tangential/sagittal anisotropy over the reliable positions."""
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
    """Geometric mean of the per-position tangential/sagittal ratios as an
    :class:`~psfkit.numerics.significance.Estimate` (σ by the delta method on the mean log;
    null 1, one-sample t-test of the logs)."""
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
    """One position's warp statistics and ``(residual flow, mask)``; ``where``: its file."""
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
