"""Fit eigen-kernel models to a measured PSF grid (``psfkit fit-eigen``).

One pass over the grid (:class:`~psfkit.alignment.GridAligner`) accumulates the per-pixel
normal equations of the chosen basis for both weight conventions at full resolution
(:mod:`psfkit.eigen`) and keeps a working copy of the aligned PSFs, on which the
per-position residuals, the leave-positions-out cross-validation of candidate bases and the
PCA (:mod:`psfkit.pca`) are computed. The result becomes a kernel file for ekdun.

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

from psfkit.alignment import (
    MIN_QUALITY,
    RELIABLE_OVERLAP,
    AlignedPsf,
    ExcludedPosition,
    GridAligner,
    NominalShifts,
    nominal_shifts,
)
from psfkit.choices import CV_BASES, SHIFT_MODES
from psfkit.eigen import (
    DEFAULT_RIDGE,
    NormalEquations,
    WorkingStack,
    check_design,
    cross_validate,
    fit_stack,
    stack_residuals,
)
from psfkit.errors import ConfigurationError
from psfkit.gain import overlap_gain
from psfkit.io.grid import FULL_LATTICE, GridPosition, PsfGrid
from psfkit.io.read_options import ReadOptions
from psfkit.kernelfile import CONVENTIONS, KernelModel
from psfkit.parallel import bounded_map
from psfkit.pca import PcaResult, principal_angles_deg, stack_pca
from psfkit.preprocess import PreprocessOptions
from psfkit.resample import binning_factor
from psfkit.weights import get_basis


@dataclass(frozen=True)
class EigenFitOptions:
    """Options of :func:`fit_eigen_grid`.

    Attributes
    ----------
    basis : str
        Weight basis of the fitted model (:func:`psfkit.weights.get_basis`).
    convention : {"sensor", "source", "auto"}
        Convention fitted at full resolution and written to the kernel file: ``"sensor"``
        (Eq. 7 as written, the default), ``"source"``, or ``"auto"`` (both, and the one with
        the lower cross-validated error is written). Both are always compared on the working
        copy.
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
        (:data:`psfkit.eigen.DEFAULT_RIDGE`: above the rounding of the sums, so that the
        pixels the data do not constrain are well-conditioned).
    min_quality : float
        Positions whose registration quality (NCC) is below this are excluded.
    strict : bool
        All or nothing: a position that fails a quality check ends the fit.
    shifts : {"affine", "registered"}
        Where each PSF is placed before the fit. ``"affine"`` (default): at the shift of the
        affine field-to-shift map fitted to the reliably registered positions
        (:func:`psfkit.alignment.nominal_shifts`), the geometry of the forward model
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

    @property
    def n_positions(self) -> int:
        """Positions the kernels were fitted to."""
        return len(self.stack.images)

    @property
    def kernels(self) -> np.ndarray:
        """Kernels ``(K, C, H, W)`` of the chosen convention, in kernel-file scale."""
        return self.full_kernels[self.convention] / self.kernel_scale

    def kernel_model(self) -> KernelModel:
        """The kernel file content (see :mod:`psfkit.kernelfile`)."""
        return KernelModel(
            kernels=self.kernels, basis=self.options.basis, convention=self.convention,
            sensor_shape=self.image_shape[1:], channels=self.channels,
            normalization="kernels divided by the mean over channels of Kbase's channel sum "
                          "(Kbase sums to about 1 per channel; colour balance and gains kept"
                          + (", PSFs gain-compensated before the fit" if
                             self.options.gain_compensate else "") + ")",
            provenance={"source": "psfkit fit-eigen", "grid": self.grid_root,
                        "fit": self.summary()},
            # measurements of this camera are taken to be stored like its PSF grid
            read_options=ReadOptions(channel_order=self.channel_order))

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers of the fit."""
        out: dict[str, Any] = {
            "basis": self.options.basis, "convention": self.convention,
            "kernel_names": list(get_basis(self.options.basis).kernel_names),
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

    ``workers`` threads register and align PSFs (default 2 on two cores).

    Raises
    ------
    GridFormatError
        The grid has no centre.
    InvalidInputError
        Too few positions or a singular design for the basis, or an unusable PSF.
    """
    options = options or EigenFitOptions()
    basis = get_basis(options.basis)
    c, h, w = grid.image_shape
    center = grid.require_center()
    missing = grid.missing()
    not_captured = f", {len(missing)} not captured" if missing else ""
    # refuse an undeterminable basis before any image is read (grid indices or field positions
    # as a proxy for the shifts), and again with the measured shifts below
    check_design(basis, _proxy_shifts(grid, center), (h, w), str(grid.root),
                 f" ({len(grid.positions)} captured{not_captured})")

    aligner = GridAligner(grid, options.preprocess, options.upsample,
                          min_quality=options.min_quality, strict=options.strict)
    full_res = CONVENTIONS if options.convention == "auto" else (options.convention,)
    equations = {conv: NormalEquations(basis, conv, (c, h, w)) for conv in full_res}
    region, factor, working = working_region(aligner.reference_support,
                                             aligner.reference_luminance, options.working_size)
    stack = WorkingStack.empty(len(grid.positions), (c, h, w), factor, region)
    reference_total = aligner.reference.sum(axis=0)
    placement: NominalShifts | None = None
    place: Callable[[GridPosition], AlignedPsf | ExcludedPosition] = aligner.try_align
    if options.shifts == "affine":
        placement, rejected = _place_by_shift_map(grid, aligner, center, progress, workers)

        def place(pos: GridPosition) -> AlignedPsf | ExcludedPosition:
            """The registration pass decided which positions are usable; each is aligned at
            its nominal shift (its quality there is measured, not checked again)."""
            if (pos.row, pos.col) in rejected:
                return rejected[(pos.row, pos.col)]
            return aligner.align(pos, shift=placement.shifts[(pos.row, pos.col)],
                                 check_quality=False)
    bar: Any = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(grid.positions), desc="fitting eigen-kernels", unit="psf")
    # registration and alignment in worker threads; the accumulation (not thread-safe) here
    excluded: list[ExcludedPosition] = []
    kept = np.ones(len(grid.positions), bool)
    try:
        for p, aligned in bounded_map(place, grid.positions, workers):
            if isinstance(aligned, ExcludedPosition):
                excluded.append(aligned)
                kept[p] = False
                if bar is not None:
                    bar.update()
                continue
            gain = overlap_gain(reference_total, aligned.image.sum(axis=0), aligned.compared)
            image = aligned.image / np.float32(gain) if options.gain_compensate \
                else aligned.image
            for eq in equations.values():
                eq.add(image, aligned.valid, aligned.shift)
            stack.put(p, aligned, image, gain)
            del aligned, image
            if bar is not None:
                bar.update()
    finally:
        if bar is not None:
            bar.close()
    stack = stack.subset(kept)
    factor = stack.factor
    shifts = stack.lattice(stack.shifts * factor, grid.grid_shape)
    check_design(basis, shifts, (h, w), str(grid.root),
                 f" ({len(excluded)} excluded{not_captured})" if excluded or missing else "")

    # the full-resolution solve (large vector operations, mostly outside the GIL) runs beside
    # the working-copy fits and the cross-validation (many small ones)
    with ThreadPoolExecutor(max_workers=1) as pool:
        solving = pool.submit(_solve_all, equations, options.ridge)
        residuals, conditioning = {}, {}
        for conv in CONVENTIONS:             # both conventions, compared on the working copy
            kernels, conditioning[conv] = fit_stack(stack, basis, conv, ridge=options.ridge)
            residuals[conv] = stack.lattice(stack_residuals(stack, kernels, basis, conv),
                                            grid.grid_shape)
        center_row = stack.row_of(center)
        cv = cross_validate(stack, list(dict.fromkeys([options.basis, *options.cv_bases])),
                            CONVENTIONS, center_row, options.folds) if options.cv_bases else None
        full_kernels = solving.result()
    del equations
    if options.convention != "auto":
        convention = options.convention
    elif cv is not None:
        errs = cv["held_out_relative_error"]
        convention = min(CONVENTIONS, key=lambda conv: errs.get(f"{options.basis}/{conv}",
                                                                math.inf))
    else:
        convention = min(CONVENTIONS, key=lambda conv: float(np.nanmedian(residuals[conv])))
    base_sums = full_kernels[convention][0].sum(axis=(1, 2))
    kernel_scale = float(np.mean(base_sums)) or 1.0

    result = GridEigenResult(
        grid_root=str(grid.root), grid_shape=grid.grid_shape, image_shape=grid.image_shape,
        channels=grid.channels, center=center, options=options, convention=convention,
        full_kernels=full_kernels, residuals=residuals, conditioning=conditioning,
        kernel_scale=kernel_scale, shifts=shifts, stack=stack, cv=cv,
        channel_order=grid.channel_order, layout=grid.layout, excluded=excluded,
        missing=missing, placement=placement,
        working={**working, "light_in_region_min": float(np.min(stack.light_in_region))
                 if stack.light_in_region is not None and len(stack.images) else 1.0})
    reliable = stack.overlap >= RELIABLE_OVERLAP
    if reliable.sum() >= 2:
        result.pca = stack_pca(stack.images, stack.valid, reliable)
        region = result.pca.region
        k = basis.n_kernels
        # the kernels cropped and averaged over the working grid's blocks
        binned_kernels = np.stack([stack.reduce(k) for k in full_kernels[convention]])
        result.angles_deg = principal_angles_deg(binned_kernels[:, :, region],
                                                 result.pca.components[:k][:, :, region])
    return result



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


def working_region(support: np.ndarray, reference: np.ndarray, working_size: int
                   ) -> tuple[tuple[slice, slice] | None, int, dict[str, Any]]:
    """Where and at what resolution the working copy holds the aligned PSFs, from the centre
    PSF's extent.

    The PSFs of the aligned grid all lie where the centre PSF lies. The working region is the
    bounding box of the centre PSF's support grown by its own size (and 8 px) on every side,
    room for PSFs that grow over the field, clipped to the sensor: defined by the PSF alone, so
    a cut-out that holds it gives the same working copy as the full frame; when that is the
    whole sensor (a caustic), the whole sensor as before issue 43. The binning is the smallest
    that brings the region to ``working_size`` px (the memory bound): a compact PSF stays at
    full resolution, several pixels wide. Its bandwidth is reported: the fraction of the
    centre PSF's power (on its support's box) above the binned grid's Nyquist frequency, which
    that binning folds.

    Parameters
    ----------
    support : numpy.ndarray
        ``(H, W)`` bool support of the centre PSF (:func:`psfkit.alignment.psf_support`).
    reference : numpy.ndarray
        ``(H, W)`` its luminance.
    working_size : int
        Longest side of the working copy, px.

    Returns
    -------
    region : (slice, slice) or None
        Rows and columns of the sensor (``None``: all of it).
    factor : int
        Binning factor.
    record : dict
        JSON-ready description (``kernel file`` provenance, ``fit.json``).
    """
    h, w = support.shape
    rows, cols = np.flatnonzero(support.any(axis=1)), np.flatnonzero(support.any(axis=0))
    if len(rows) == 0:
        rows, cols = np.arange(h), np.arange(w)
    box = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    extent = [box[0].stop - box[0].start, box[1].stop - box[1].start]
    grown = tuple(slice(max(0, sl.start - size - 8), min(n, sl.stop + size + 8))
                  for sl, size, n in zip(box, extent, (h, w), strict=True))
    crop = (grown[0].stop - grown[0].start, grown[1].stop - grown[1].start)
    region = None if crop == (h, w) else (grown[0], grown[1])
    shape = (h, w) if region is None else crop
    factor = binning_factor(shape, working_size)
    record = {"chosen_from": "the whole sensor (the PSF fills it)" if region is None else
              "the centre PSF's support",
              "origin_px": [0, 0] if region is None else [region[0].start, region[1].start],
              "shape_px": list(shape), "binning": factor, "psf_extent_px": extent,
              "aliased_power": aliased_power(reference[box], factor)}
    return region, factor, record


def aliased_power(image: np.ndarray, factor: int) -> float:
    """Fraction of an image's (non-DC) power above the Nyquist frequency of a grid binned by
    ``factor`` (what that binning folds): 0 for ``factor`` 1."""
    import scipy.fft as sfft

    if factor <= 1 or min(image.shape) < 2:
        return 0.0
    power = np.abs(sfft.rfft2(image - image.mean(), workers=-1)) ** 2
    gy = np.abs(np.fft.fftfreq(image.shape[0]))[:, None]
    gx = np.fft.rfftfreq(image.shape[1])[None, :]
    total = float(power.sum())
    limit = 0.5 / factor
    return float(power[(gy > limit) | (gx > limit)].sum()) / total if total > 0 else 0.0


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
