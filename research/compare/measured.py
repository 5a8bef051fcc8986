"""The measured side of a comparison, on the comparison grid: from a PSF grid
(:func:`measure_modes`: eigen-kernels fitted with the learned file's basis and convention, top
PCA modes, warps of :mod:`research.compare.warps`) or from another kernel file
(:func:`modes_from_kernel_file`: its kernels only; no warps or PCA modes, ``null`` in
``compare.json``)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.calibration.alignment import GridAligner
from psfkit.calibration.preprocess import luminance
from psfkit.errors import InvalidInputError, ModelFileError
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.fitting.grid.result import GridEigenResult
from psfkit.forward.kernelfile import KernelModel
from psfkit.forward.weights import get_basis
from psfkit.io.grid import PsfGrid
from psfkit.io.grid_validation import read_grid
from research.compare.displacement import DisplacementMap, comparison_mask
from research.compare.options import CompareOptions
from research.compare.resampling import check_shapes, pad_kernels, resample
from research.compare.warps import WARP_AXES, measured_warp, measured_warps_joint


@dataclass
class MeasuredModes:
    """What a PSF grid (or kernel file) says about the eigen-kernels, on the comparison grid.

    Attributes
    ----------
    model : KernelModel
        Measured eigen-kernels resampled to ``sensor_shape`` ``(H, W)`` (the learned sensor).
    warps : dict
        Kernel name → warp-predicted :class:`DisplacementMap` relative to ``Kbase``.
    warp_positions : dict
        Kernel name (or ``"all"``) → the positions used (row, col, shift, weight change,
        overlap, warp RMS).
    pca_components, pca_region : numpy.ndarray or None
        ``(r, C, h, w)`` top uncentred PCA modes on the fit's working grid; ``(h, w)`` bool
        pixels they use.
    fit : GridEigenResult or None
        The grid fit (``None`` for a kernel file).
    notes : list of str
        What was resampled, skipped or approximated.
    source : str
        The grid folder or kernel file.
    """

    model: KernelModel
    sensor_shape: tuple[int, int]
    warps: dict[str, DisplacementMap]
    warp_positions: dict[str, list[dict[str, Any]]]
    pca_components: np.ndarray | None
    pca_region: np.ndarray | None
    fit: GridEigenResult | None = field(repr=False)
    notes: list[str] = field(default_factory=list)
    source: str = ""

    def to_dict(self) -> dict[str, Any]:
        # a kernel file: its kernels only (no warps, PCA modes or fit)
        source = {"kernels": self.source} if self.fit is None else {
            "grid": self.fit.grid_root, "grid_shape": list(self.fit.grid_shape),
            "image_shape": list(self.fit.image_shape)}
        return {**source, "comparison_shape": list(self.sensor_shape),
                "basis": self.model.basis, "convention": self.model.convention,
                "warp_positions": self.warp_positions,
                "warp_rms_px": {k: w.rms() for k, w in self.warps.items()},
                "pca_modes": None if self.pca_components is None
                else len(self.pca_components),
                "fit": None if self.fit is None else self.fit.summary(), "notes": self.notes}


def _on_grid(model: KernelModel, kernels: np.ndarray, sensor_shape: tuple[int, int]
             ) -> KernelModel:
    """``kernels`` on the comparison grid with ``model``'s basis, convention and metadata."""
    return KernelModel(kernels=kernels, basis=model.basis, convention=model.convention,
                       sensor_shape=tuple(sensor_shape), channels=model.channels,
                       normalization=model.normalization, provenance=model.provenance)


def load_grid(measured: PsfGrid | str | os.PathLike) -> PsfGrid:
    """A :class:`PsfGrid` from a grid or a grid folder (validated, pixels checked lazily)."""
    if isinstance(measured, PsfGrid):
        return measured
    path = Path(measured)
    if not path.is_dir():
        raise InvalidInputError(f"{path}: not a PSF-grid folder")
    return read_grid(path, check_pixels=False)


def measure_modes(measured: PsfGrid | str | os.PathLike, basis: str, convention: str,
                  sensor_shape: tuple[int, int], options: CompareOptions | None = None,
                  progress: bool = False) -> MeasuredModes:
    """Fit the grid and measure its warp fields and PCA modes on the comparison grid.

    Parameters
    ----------
    basis, convention : str
        Those of the learned file.
    sensor_shape : (int, int)
        The comparison grid ``(H, W)`` the PSFs are resampled to (same aspect ratio).

    Raises
    ------
    GridFormatError
        Not a grid, or no centre.
    InvalidInputError
        Aspect ratios differ, or the grid cannot determine the basis.
    """
    options = options or CompareOptions()
    grid = load_grid(measured)
    _, h, w = grid.image_shape
    check_shapes(sensor_shape, (h, w), str(grid.root))
    notes = []
    if (h, w) != tuple(sensor_shape):
        notes.append(f"grid PSFs {h}x{w} resampled to the kernel file's sensor "
                     f"{sensor_shape[0]}x{sensor_shape[1]} (factor {h / sensor_shape[0]:.3g}); "
                     "displacements are in kernel-file pixels")
    fit_options = options.fit or EigenFitOptions(basis=basis, convention=convention,
                                                 cv_bases=(), preprocess=options.preprocess)
    fit = fit_eigen_grid(grid, fit_options, progress=progress)
    fitted = fit.kernel_model()
    model = _on_grid(fitted, resample(fitted.kernels, tuple(sensor_shape)), sensor_shape)
    base_lum = luminance(model.kernels[0])
    mask = comparison_mask(base_lum, options)
    aligner = GridAligner(grid, fit_options.preprocess, fit_options.upsample)
    warps, positions = {}, {}
    if options.warp_positions == "all":
        warps, used, more = measured_warps_joint(aligner, basis, convention, (h, w),
                                                  tuple(sensor_shape), mask, options)
        notes.extend(more)
        positions = {"all": used}
    for name in get_basis(basis).kernel_names[1:] if options.warp_positions == "axes" else ():
        if name not in WARP_AXES:
            notes.append(f"kernel {name!r}: no single-axis warp predicts it; kernel and PCA "
                         "comparisons only")
            continue
        warp, used, more = measured_warp(aligner, name, basis, convention, (h, w),
                                          tuple(sensor_shape), mask, options)
        notes.extend(more)
        positions[name] = used
        if warp is not None:
            warps[name] = warp
    pca = fit.pca
    if pca is None:
        notes.append("too few reliable positions for a PCA of the grid")
    return MeasuredModes(model=model, sensor_shape=tuple(sensor_shape), warps=warps,
                         warp_positions=positions,
                         pca_components=None if pca is None else pca.components,
                         pca_region=None if pca is None else pca.region, fit=fit, notes=notes,
                         source=str(grid.root))


def modes_from_kernel_file(measured: KernelModel, where: str, basis: str, convention: str,
                           sensor_shape: tuple[int, int]) -> MeasuredModes:
    """The measured side from a kernel file: its kernels on the comparison grid.

    Parameters
    ----------
    measured : KernelModel
        A grid fit, a pairs fit, an oracle; named ``where`` in messages and ``compare.json``.
    basis, convention : str
        Those of the learned file (must agree).
    sensor_shape : (int, int)
        The comparison grid; the kernels are zero-padded to their sensor and resampled to it.

    Raises
    ------
    ModelFileError
        Basis or convention differ, or a single kernel.
    InvalidInputError
        Aspect ratios differ.
    """
    if measured.kernels.shape[0] < 2:
        raise ModelFileError(f"{where}: has a single kernel: nothing to compare the "
                             "corrections with")
    if measured.basis != basis or measured.convention != convention:
        raise ModelFileError(f"{where}: basis/convention {measured.basis}/{measured.convention} "
                             f"differ from the learned file's {basis}/{convention}")
    own = tuple(measured.sensor_shape)
    check_shapes(tuple(sensor_shape), own, where)
    kernels = pad_kernels(measured.kernels, own)
    notes = []
    if own != tuple(sensor_shape):
        kernels = resample(kernels, tuple(sensor_shape))
        notes.append(f"{where}: kernels {own[0]}x{own[1]} resampled to the learned file's sensor "
                     f"{sensor_shape[0]}x{sensor_shape[1]}; displacements are in learned-file "
                     "pixels")
    notes.append("the measured side is a kernel file: no warps and no PCA modes to compare with")
    model = _on_grid(measured, kernels.astype(np.float32), sensor_shape)
    return MeasuredModes(model=model, sensor_shape=tuple(sensor_shape), warps={},
                         warp_positions={}, pca_components=None, pca_region=None, fit=None,
                         notes=notes, source=where)
