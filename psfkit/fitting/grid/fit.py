"""Fit eigen-kernel models to a measured PSF grid (``psfkit fit-eigen``).

One pass over the grid accumulates the per-pixel normal equations at full resolution
(:mod:`psfkit.fitting.grid.eigen`) and keeps a working copy of the aligned PSFs
(:func:`~psfkit.fitting.grid.working_stack.working_region`: a crop around a compact PSF, or the
whole sensor binned to at most ``working_size`` px) for residuals, cross-validation and PCA.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from psfkit.calibration.alignment import (
    RELIABLE_OVERLAP,
    AlignedPsf,
    ExcludedPosition,
    GridAligner,
)
from psfkit.calibration.gain import overlap_gain
from psfkit.calibration.nominal_shifts import NominalShifts, nominal_shifts
from psfkit.choices import CV_BASES_ALL
from psfkit.fitting.grid.design import check_design
from psfkit.fitting.grid.eigen import NormalEquations
from psfkit.fitting.grid.heldout import judge
from psfkit.fitting.grid.options import AUTO, EigenFitOptions
from psfkit.fitting.grid.pca import principal_angles_deg, stack_pca
from psfkit.fitting.grid.result import GridEigenResult
from psfkit.fitting.grid.stack_fit import CrossValidation, fit_stack, stack_residuals
from psfkit.fitting.grid.working_stack import WorkingStack, working_region
from psfkit.fitting.verdict import Verdict
from psfkit.forward.kernelfile import CONVENTIONS
from psfkit.forward.weights import get_basis
from psfkit.io.grid import GridPosition, PsfGrid
from psfkit.numerics.parallel import bounded_map


def _solve_all(equations: dict[str, NormalEquations], ridge: float) -> dict[str, np.ndarray]:
    return {conv: eq.solve(ridge, conditioning=False)[0] for conv, eq in equations.items()}


def fit_eigen_grid(grid: PsfGrid, options: EigenFitOptions | None = None,
                   progress: bool = False, workers: int | None = None) -> GridEigenResult:
    """Fit the eigen-kernel model of ``options.basis`` to a PSF grid, both conventions.

    ``workers`` threads register and align PSFs. With ``options.basis == "auto"`` the verdict
    chooses basis and convention on the working copy first, then the PSFs are read again for the
    one full-resolution fit.

    Raises
    ------
    GridFormatError
        The grid has no centre.
    InvalidInputError
        Too few positions or a singular design for the basis, or an unusable PSF.
    """
    options = options or EigenFitOptions()
    auto = options.basis == AUTO
    c, h, w = grid.image_shape
    center = grid.require_center()
    missing = grid.missing()
    not_captured = f", {len(missing)} not captured" if missing else ""
    # refuse an undeterminable basis before any image is read (grid indices or field positions
    # as a proxy for the shifts), and again with the measured shifts below
    check_design(get_basis("si" if auto else options.basis), _proxy_shifts(grid, center),
                 (h, w), str(grid.root), f" ({len(grid.positions)} captured{not_captured})")

    aligner = GridAligner(grid, options.preprocess, options.upsample,
                          min_quality=options.min_quality, strict=options.strict)
    placement, place = _placement(grid, aligner, center, options, progress, workers)
    region, factor, working = working_region(aligner.reference_support,
                                             aligner.reference_luminance, options.working_size)
    full_res = () if auto else \
        CONVENTIONS if options.convention == "auto" else (options.convention,)
    equations = {conv: NormalEquations(get_basis(options.basis), conv, (c, h, w))
                 for conv in full_res}
    stack, excluded = _accumulate(grid, aligner, place, equations, options, progress,
                                  workers, "fitting eigen-kernels", (region, factor))
    shifts = stack.lattice(stack.shifts * factor, grid.grid_shape)
    left_out = f" ({len(excluded)} excluded{not_captured})" if excluded or missing else ""
    if not auto:
        check_design(get_basis(options.basis), shifts, (h, w), str(grid.root), left_out)
    center_row = stack.row_of(center)

    # the full-resolution solve (large vector operations, mostly outside the GIL) runs beside
    # the working-copy fits and the cross-validation (many small ones)
    with ThreadPoolExecutor(max_workers=1) as pool:
        solving = pool.submit(_solve_all, equations, options.ridge)
        cv_bases = list(dict.fromkeys(
            [*([] if auto else [options.basis]), *(CV_BASES_ALL if auto else ()),
             *options.cv_bases]))
        validation, verdict = None, None
        if cv_bases:
            effects = {"shift": placement.fit.distortion} \
                if placement is not None and placement.fit is not None else {}
            validation, verdict = judge(stack, center_row, (h, w), cv_bases, options.folds,
                                        effects, progress)
        full_kernels = solving.result()
    del equations
    basis, convention = _choose(options, validation, verdict)
    if auto:
        check_design(get_basis(basis), shifts, (h, w), str(grid.root), left_out)
        equations = {convention: NormalEquations(get_basis(basis), convention, (c, h, w))}
        _accumulate(grid, aligner, place, equations, options, progress, workers,
                    f"fitting {basis}/{convention}", (region, factor), keep_stack=False)
        full_kernels = _solve_all(equations, options.ridge)
        del equations
    residuals, conditioning = {}, {}
    for conv in CONVENTIONS:             # both conventions, compared on the working copy
        kernels, conditioning[conv] = fit_stack(stack, get_basis(basis), conv,
                                                ridge=options.ridge)
        residuals[conv] = stack.lattice(stack_residuals(stack, kernels, get_basis(basis), conv),
                                        grid.grid_shape)
    base_sums = full_kernels[convention][0].sum(axis=(1, 2))
    kernel_scale = float(np.mean(base_sums)) or 1.0

    result = GridEigenResult(
        grid_root=str(grid.root), grid_shape=grid.grid_shape, image_shape=grid.image_shape,
        channels=grid.channels, center=center, options=options, convention=convention,
        full_kernels=full_kernels, residuals=residuals, conditioning=conditioning,
        kernel_scale=kernel_scale, shifts=shifts, stack=stack,
        cv=None if validation is None else validation.to_dict(),
        channel_order=grid.channel_order, layout=grid.layout, excluded=excluded,
        missing=missing, placement=placement, basis=basis, cross_validation=validation,
        verdict=verdict,
        working={**working, "light_in_region_min": float(np.min(stack.light_in_region))
                 if stack.light_in_region is not None and len(stack.images) else 1.0})
    _principal_angles(result, get_basis(basis).n_kernels)
    return result


def _placement(grid: PsfGrid, aligner: GridAligner, center: tuple[int, int],
               options: EigenFitOptions, progress: bool, workers: int | None
               ) -> tuple[NominalShifts | None, Callable[[GridPosition],
                                                         AlignedPsf | ExcludedPosition]]:
    """Where each PSF is aligned for the fit, and the function aligning it there: with
    ``shifts="affine"``, after a registration pass, at the affine map's nominal shift (its quality
    there measured, not checked again)."""
    if options.shifts != "affine":
        return None, aligner.try_align
    rejected: dict[tuple[int, int], ExcludedPosition] = {}
    accepted: list[GridPosition] = []
    shifts: list[tuple[float, float]] = []
    overlaps: list[float] = []
    for _, aligned in _aligned(grid, aligner.try_align, workers, progress, "registering"):
        if isinstance(aligned, ExcludedPosition):
            rejected[(aligned.row, aligned.col)] = aligned
        else:
            accepted.append(aligned.position)
            shifts.append(aligned.shift)
            overlaps.append(aligned.support_overlap)
        del aligned
    placement = nominal_shifts(accepted, np.array(shifts), np.array(overlaps), center)

    def place(pos: GridPosition) -> AlignedPsf | ExcludedPosition:
        if (pos.row, pos.col) in rejected:
            return rejected[(pos.row, pos.col)]
        return aligner.align(pos, shift=placement.shifts[(pos.row, pos.col)],
                             check_quality=False)
    return placement, place


def _accumulate(grid: PsfGrid, aligner: GridAligner,
                place: Callable[[GridPosition], AlignedPsf | ExcludedPosition],
                equations: dict[str, NormalEquations], options: EigenFitOptions,
                progress: bool, workers: int | None, description: str,
                working: tuple[tuple[slice, slice] | None, int], keep_stack: bool = True
                ) -> tuple[WorkingStack, list[ExcludedPosition]]:
    """One pass adding every usable PSF to ``equations`` and (``keep_stack``) to the working copy
    of region and binning ``working``; returns that copy and the excluded positions."""
    region, factor = working
    stack = WorkingStack.empty(len(grid.positions) if keep_stack else 0, grid.image_shape,
                               factor, region)
    reference_total = aligner.reference.sum(axis=0)
    excluded: list[ExcludedPosition] = []
    kept = np.ones(len(grid.positions), bool)
    # the accumulation (not thread-safe) here
    for p, aligned in _aligned(grid, place, workers, progress, description):
        if isinstance(aligned, ExcludedPosition):
            excluded.append(aligned)
            kept[p] = False
        else:
            gain = overlap_gain(reference_total, aligned.image.sum(axis=0),
                                aligner.gain_region(aligned))
            image = aligned.image / np.float32(gain) if options.gain_compensate \
                else aligned.image
            for eq in equations.values():
                eq.add(image, aligned.valid, aligned.shift)
            if keep_stack:
                stack.put(p, aligned, image, gain)
            del aligned, image
    return (stack.subset(kept) if keep_stack else stack), excluded


def _aligned(grid: PsfGrid, place: Callable[[GridPosition], AlignedPsf | ExcludedPosition],
             workers: int | None, progress: bool, description: str
             ) -> Iterator[tuple[int, AlignedPsf | ExcludedPosition]]:
    """``(index, place(position))`` of every position, run in worker threads."""
    from tqdm.auto import tqdm

    with tqdm(total=len(grid.positions), desc=description, unit="psf",
              disable=not progress) as bar:
        for item in bounded_map(place, grid.positions, workers):
            yield item
            del item                 # the caller dropped its PSF: hold none while waiting
            bar.update()


def _choose(options: EigenFitOptions, validation: CrossValidation | None,
            verdict: Verdict | None) -> tuple[str, str]:
    """The basis and convention written to the kernel file."""
    if options.basis == AUTO:
        if verdict is None:
            return "si", "sensor"
        return verdict.basis, verdict.convention or "sensor"
    if options.convention != "auto":
        return options.basis, options.convention
    if validation is not None:
        errs = validation.to_dict()["held_out_relative_error"]
        return options.basis, min(CONVENTIONS, key=lambda conv: errs.get(
            f"{options.basis}/{conv}", math.inf))
    return options.basis, "sensor"


def _principal_angles(result: GridEigenResult, n_kernels: int) -> None:
    """The PCA of the reliable positions and its principal angles to the kernels (working grid)."""
    stack = result.stack
    reliable = stack.overlap >= RELIABLE_OVERLAP
    if reliable.sum() < 2:
        return
    result.pca = stack_pca(stack.images, stack.valid, reliable)
    region = result.pca.region
    # the kernels cropped and averaged over the working grid's blocks
    binned_kernels = np.stack([stack.reduce(k) for k in result.full_kernels[result.convention]])
    result.angles_deg = principal_angles_deg(binned_kernels[:, :, region],
                                             result.pca.components[:n_kernels][:, :, region])


def _proxy_shifts(grid: PsfGrid, center: tuple[int, int]) -> np.ndarray:
    """``(P, 2)`` stand-ins for the shifts before any image is read: grid indices (a lattice) or
    field positions (an irregular scan) spread over the sensor."""
    _, h, w = grid.image_shape
    if grid.is_irregular:
        coords = grid.monitor_px() if grid.monitor_px() is not None else grid.field_deg()
        assert coords is not None
        rel = coords[0] - coords[center]
        span = np.maximum(np.abs(rel).max(axis=0), 1e-12)
        return rel / span * np.array([w, h]) / 2
    n_rows, n_cols = grid.grid_shape
    index = np.array([(p.row, p.col) for p in grid.positions], dtype=np.float64)
    return np.stack([(index[:, 1] - center[1]) * w / max(n_cols, 2),
                     (index[:, 0] - center[0]) * h / max(n_rows, 2)], axis=-1)
