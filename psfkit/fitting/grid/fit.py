"""Fit eigen-kernel models to a measured PSF grid (``psfkit fit-eigen``).

One pass over the grid (:class:`~psfkit.calibration.alignment.GridAligner`) accumulates the
per-pixel
normal equations of the chosen basis for both weight conventions at full resolution
(:mod:`psfkit.fitting.grid.eigen`) and keeps a working copy of the aligned PSFs, on which the
per-position residuals, the leave-positions-out cross-validation of candidate bases and the
PCA (:mod:`psfkit.fitting.grid.pca`) are computed. The result becomes a kernel file for ekdun.

The working copy's resolution follows the PSF (:func:`working_region`): a compact PSF (a few
pixels on a large frame) is kept on a crop around the centre PSF's support at full
resolution; a PSF that fills the sensor (a caustic) is kept whole, binned to at most
``working_size`` px. Either way at most ``working_size``² pixels per channel and position.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psfkit.calibration.alignment import (
    MIN_QUALITY,
    RELIABLE_OVERLAP,
    AlignedPsf,
    ExcludedPosition,
    GridAligner,
    NominalShifts,
    nominal_shifts,
)
from psfkit.calibration.gain import overlap_gain
from psfkit.calibration.preprocess import PreprocessOptions
from psfkit.choices import CV_BASES, CV_BASES_ALL, SHIFT_MODES
from psfkit.errors import ConfigurationError
from psfkit.fitting.grid.design import check_design
from psfkit.fitting.grid.eigen import DEFAULT_RIDGE, NormalEquations
from psfkit.fitting.grid.heldout import judge
from psfkit.fitting.grid.pca import PcaResult, principal_angles_deg, stack_pca
from psfkit.fitting.grid.stack_fit import (
    CrossValidation,
    fit_stack,
    kernel_difference_estimates,
    stack_residuals,
)
from psfkit.fitting.grid.working_stack import WorkingStack, working_region
from psfkit.fitting.verdict import Verdict
from psfkit.forward.kernelfile import CONVENTIONS, KernelModel
from psfkit.forward.weights import get_basis
from psfkit.io.grid import FULL_LATTICE, GridPosition, PsfGrid
from psfkit.io.jsonable import jsonable
from psfkit.io.read_options import ReadOptions
from psfkit.numerics.parallel import bounded_map
from psfkit.numerics.significance import Estimate, undetermined

#: ``EigenFitOptions.basis`` (``psfkit fit-eigen --basis auto``): the verdict's model.
AUTO = "auto"


@dataclass(frozen=True)
class EigenFitOptions:
    """Options of :func:`fit_eigen_grid`.

    Attributes
    ----------
    basis : str
        Weight basis of the fitted model (:func:`psfkit.forward.weights.get_basis`), or ``"auto"``:
        the basis *and* convention of the verdict (:mod:`psfkit.fitting.verdict`; ``"si"`` when the
        PSF shape does not change over the field beyond noise), every basis of
        :data:`psfkit.choices.CV_BASES_ALL` cross-validated, one full-resolution fit.
    convention : {"sensor", "source", "auto"}
        Convention fitted at full resolution and written to the kernel file: ``"sensor"``
        (Eq. 7 as written, the default), ``"source"``, or ``"auto"`` (both, and the one with
        the lower cross-validated error is written). Both are always compared on the working
        copy. With ``basis="auto"`` the verdict chooses it (``"sensor"`` for ``"si"``, where
        both are the same model).
    gain_compensate : bool
        Divide every PSF by its gain before fitting (kernels then describe shape only); by
        default the gains stay in the kernels, as the forward model needs them.
    cv_bases : tuple of str
        Bases compared by leave-positions-out cross-validation (empty: no CV).
    folds : int
        Cross-validation groups of positions.
    working_size : int
        Longest side (px) of the binned working copy used for CV, residuals and PCA.
    ridge : float
        Relative weight of the prior pulling correction kernels towards the base kernel
        (:data:`psfkit.fitting.grid.eigen.DEFAULT_RIDGE`: above the rounding of the sums, so that
        the
        pixels the data do not constrain are well-conditioned).
    min_quality : float
        Positions whose registration quality (NCC) is below this are excluded.
    strict : bool
        All or nothing: a position that fails a quality check ends the fit.
    shifts : {"affine", "registered"}
        Where each PSF is placed before the fit. ``"affine"`` (default): at the shift of the
        affine field-to-shift map fitted to the reliably registered positions
        (:func:`psfkit.calibration.alignment.nominal_shifts`), the geometry of the forward model
        ``y = crop(K * pad(x))``, so that distortion and the caustic's deformation stay in
        the kernels. ``"registered"``: at each PSF's own registered shift (before 2026-11-25;
        it removes that part, and is biased where a PSF is mostly off the sensor).
    """

    basis: str = "paper"
    convention: str = "sensor"
    gain_compensate: bool = False
    cv_bases: tuple[str, ...] = CV_BASES
    folds: int = 9
    working_size: int = 256
    ridge: float = DEFAULT_RIDGE
    upsample: int = 100
    preprocess: PreprocessOptions = field(default_factory=PreprocessOptions)
    min_quality: float = MIN_QUALITY
    strict: bool = False
    shifts: str = "affine"

    def __post_init__(self) -> None:
        # every message names the flag of psfkit fit-eigen, never a Python field
        for flag_name, names in (("--basis", (self.basis,)), ("--cv-bases", self.cv_bases)):
            for name in names:
                if flag_name == "--basis" and name == AUTO:
                    continue
                try:
                    get_basis(name)
                except ConfigurationError as exc:
                    raise ConfigurationError(f"{flag_name}: {exc}") from None
        if self.convention not in (*CONVENTIONS, "auto"):
            raise ConfigurationError(f"--convention must be one of {', '.join(CONVENTIONS)} "
                                     f"or auto, got {self.convention!r}")
        if self.shifts not in SHIFT_MODES:
            raise ConfigurationError(f"--shifts must be one of {', '.join(SHIFT_MODES)}, got "
                                     f"{self.shifts!r}")
        if self.folds < 2:
            raise ConfigurationError(f"--folds must be >= 2, got {self.folds}")
        if self.working_size < 32:
            raise ConfigurationError("EigenFitOptions: working_size must be >= 32 (no flag "
                                     "sets it)")


@dataclass
class GridEigenResult:
    """Everything :func:`fit_eigen_grid` measured."""

    grid_root: str
    grid_shape: tuple[int, int]
    image_shape: tuple[int, int, int]
    channels: tuple[str, ...]
    center: tuple[int, int]
    options: EigenFitOptions
    convention: str
    full_kernels: dict[str, np.ndarray] = field(repr=False)       # convention → (K, C, H, W)
    residuals: dict[str, np.ndarray] = field(repr=False)          # convention → (N, M)
    conditioning: dict[str, np.ndarray] = field(repr=False)       # convention → (h, w)
    shifts: np.ndarray = field(repr=False)
    stack: WorkingStack = field(repr=False)
    kernel_scale: float = 1.0
    cv: dict[str, Any] | None = None
    pca: PcaResult | None = None
    channel_order: str = "RGB"   # of the grid's files on disk (recorded in the kernel file)
    angles_deg: np.ndarray | None = None
    layout: str = FULL_LATTICE
    excluded: list[ExcludedPosition] = field(default_factory=list)
    missing: list[tuple[int, int]] = field(default_factory=list)
    placement: NominalShifts | None = None      # None: each PSF at its registered shift
    working: dict[str, Any] = field(default_factory=dict)   # how the working copy was chosen
    basis: str = ""                             # the fitted basis ("auto" resolved)
    cross_validation: CrossValidation | None = field(default=None, repr=False)
    verdict: Verdict | None = None

    @property
    def basis_name(self) -> str:
        """The fitted basis (``options.basis``, or what ``"auto"`` chose)."""
        return self.basis or self.options.basis

    def kernel_differences(self) -> dict[str, Estimate]:
        """``"Kv − Kbase"``-style names to each correction kernel's relative difference
        ``‖K_k − K_0‖/‖K_0‖`` on the working copy, with its jackknife 1σ and significance
        (:func:`psfkit.fitting.grid.stack_fit.kernel_difference_estimates`); empty for ``"si"``."""
        names = get_basis(self.basis_name).kernel_names
        if len(names) < 2:
            return {}
        labels = [f"K{name} − K{names[0]}" for name in names[1:]]
        stats = None if self.cross_validation is None else \
            self.cross_validation.kernel_differences.get(f"{self.basis_name}/{self.convention}")
        if stats is None:
            return {label: undetermined("no cross-validation (--cv-bases none)")
                    for label in labels}
        p_value = math.nan
        if self.verdict is not None and self.verdict.field_test.determined:
            p_value = self.verdict.field_test.p_value
        return dict(zip(labels, kernel_difference_estimates(*stats, p_value), strict=True))

    @property
    def n_positions(self) -> int:
        """Positions the kernels were fitted to."""
        return len(self.stack.images)

    @property
    def kernels(self) -> np.ndarray:
        """Kernels ``(K, C, H, W)`` of the chosen convention, in kernel-file scale."""
        return self.full_kernels[self.convention] / self.kernel_scale

    def kernel_model(self) -> KernelModel:
        """The kernel file content (see :mod:`psfkit.forward.kernelfile`)."""
        return KernelModel(
            kernels=self.kernels, basis=self.basis_name, convention=self.convention,
            sensor_shape=self.image_shape[1:], channels=self.channels,
            normalization="kernels divided by the mean over channels of Kbase's channel sum "
                          "(Kbase sums to about 1 per channel; colour balance and gains kept"
                          + (", PSFs gain-compensated before the fit" if
                             self.options.gain_compensate else "") + ")",
            # NaN/Inf (an undetermined σ, an infinite z) as null: the metadata is strict JSON
            provenance={"source": "psfkit fit-eigen", "grid": self.grid_root,
                        "fit": jsonable(self.summary())},
            # measurements of this camera are taken to be stored like its PSF grid
            read_options=ReadOptions(channel_order=self.channel_order))

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers of the fit."""
        out: dict[str, Any] = {
            "basis": self.basis_name, "convention": self.convention,
            "kernel_names": list(get_basis(self.basis_name).kernel_names),
            "gain_compensated": self.options.gain_compensate,
            "working_binning": self.stack.factor,
            "working_region": self.working,
            "shifts": (self.placement.to_dict() if self.placement is not None
                       else {"source": "registered"}),
            "in_sample_relative_error": {
                conv: {"median": float(np.nanmedian(res)), "max": float(np.nanmax(res))}
                for conv, res in self.residuals.items()},
            "unconstrained_pixel_fraction": {
                conv: float(np.mean(cond < 1e-6)) for conv, cond in self.conditioning.items()},
        }
        if self.cv is not None:
            out["cross_validation"] = self.cv
        if self.verdict is not None:
            out["verdict"] = self.verdict.to_dict()
            out["kernel_differences"] = {name: e.to_dict()
                                         for name, e in self.kernel_differences().items()}
        if self.pca is not None:
            out["pca"] = self.pca.to_dict()
        if self.angles_deg is not None:
            out["principal_angles_deg_eigen_vs_pca"] = self.angles_deg.tolist()
        if self.layout != FULL_LATTICE or self.excluded:    # (a full grid's record as before)
            out["layout"] = self.layout
            out["positions_fitted"] = self.n_positions
            out["missing"] = [list(index) for index in self.missing]
            out["excluded"] = [e.to_dict() for e in self.excluded]
        return out


def _solve_all(equations: dict[str, NormalEquations], ridge: float) -> dict[str, np.ndarray]:
    return {conv: eq.solve(ridge, conditioning=False)[0] for conv, eq in equations.items()}


def fit_eigen_grid(grid: PsfGrid, options: EigenFitOptions | None = None,
                   progress: bool = False, workers: int | None = None) -> GridEigenResult:
    """Fit the eigen-kernel model of ``options.basis`` to a PSF grid, both conventions.

    ``workers`` threads register and align PSFs (default 2 on two cores). With
    ``options.basis == "auto"`` the verdict (:mod:`psfkit.fitting.verdict`) chooses the basis and
    the
    convention before the one full-resolution fit (the aligned PSFs are read once more for
    it: the working copy decides, the full-resolution sums are of the chosen model only).

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
    """Where each PSF is aligned for the fit, and the function that aligns it there."""
    if options.shifts != "affine":
        return None, aligner.try_align
    placement, rejected = _place_by_shift_map(grid, aligner, center, progress, workers)

    def place(pos: GridPosition) -> AlignedPsf | ExcludedPosition:
        """The registration pass decided which positions are usable; each is aligned at
        its nominal shift (its quality there is measured, not checked again)."""
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
    """One pass over the grid: every usable PSF aligned (``place``), added to the
    full-resolution ``equations`` and (``keep_stack``) to the working copy (``working``: its
    region and binning, :func:`working_region`). Returns
    the working copy of the measured positions and the excluded ones."""
    c, h, w = grid.image_shape
    region, factor = working
    stack = WorkingStack.empty(len(grid.positions) if keep_stack else 0, (c, h, w), factor,
                               region)
    reference_total = aligner.reference.sum(axis=0)
    bar: Any = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(grid.positions), desc=description, unit="psf")
    # registration and alignment in worker threads; the accumulation (not thread-safe) here
    excluded: list[ExcludedPosition] = []
    kept = np.ones(len(grid.positions), bool)
    try:
        for p, aligned in bounded_map(place, grid.positions, workers):
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
            if bar is not None:
                bar.update()
    finally:
        if bar is not None:
            bar.close()
    return (stack.subset(kept) if keep_stack else stack), excluded


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
    """The PCA of the reliable positions and the principal angles between its top subspace
    and the fitted kernels (averaged over the working grid's blocks)."""
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


def _place_by_shift_map(grid: PsfGrid, aligner: GridAligner, center: tuple[int, int],
                        progress: bool, workers: int | None
                        ) -> tuple[NominalShifts, dict[tuple[int, int], ExcludedPosition]]:
    """The registration pass of ``shifts="affine"``: every position registered (and checked)
    as the characterization does, keeping only its shift and overlap; the affine map of
    those shifts; and the positions it rejected."""
    rejected: dict[tuple[int, int], ExcludedPosition] = {}
    accepted: list[GridPosition] = []
    shifts: list[tuple[float, float]] = []
    overlaps: list[float] = []
    bar: Any = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(grid.positions), desc="registering", unit="psf")
    try:
        for _, aligned in bounded_map(aligner.try_align, grid.positions, workers):
            if isinstance(aligned, ExcludedPosition):
                rejected[(aligned.row, aligned.col)] = aligned
            else:
                accepted.append(aligned.position)
                shifts.append(aligned.shift)
                overlaps.append(aligned.support_overlap)
            del aligned
            if bar is not None:
                bar.update()
    finally:
        if bar is not None:
            bar.close()
    return nominal_shifts(accepted, np.array(shifts), np.array(overlaps), center), rejected


def _proxy_shifts(grid: PsfGrid, center: tuple[int, int]) -> np.ndarray:
    """Stand-ins for the shifts of the captured positions before any image is read: grid
    indices spread over the sensor (a lattice), or field positions scaled likewise (an
    irregular scan). ``(P, 2)``."""
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
