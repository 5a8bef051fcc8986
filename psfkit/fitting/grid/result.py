"""The result of ``psfkit fit-eigen`` (:class:`GridEigenResult`): both conventions' kernels,
what the working copy measured, the JSON summary and the kernel file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psfkit.calibration.alignment import ExcludedPosition
from psfkit.calibration.nominal_shifts import NominalShifts
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.fitting.grid.pca import PcaResult
from psfkit.fitting.grid.stack_fit import CrossValidation, kernel_difference_estimates
from psfkit.fitting.grid.working_stack import WorkingStack
from psfkit.fitting.verdict import Verdict
from psfkit.forward.kernelfile import KernelModel
from psfkit.forward.weights import get_basis
from psfkit.io.grid import FULL_LATTICE
from psfkit.io.jsonable import jsonable
from psfkit.io.read_options import ReadOptions
from psfkit.numerics.significance import Estimate, undetermined


@dataclass
class GridEigenResult:
    """Everything :func:`psfkit.fitting.grid.fit.fit_eigen_grid` measured."""

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
        """Each correction kernel's ``‖K_k − K_0‖/‖K_0‖`` on the working copy with its jackknife 1σ
        (``"Kv − Kbase"``-style names); empty for ``"si"``."""
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
        if self.layout != FULL_LATTICE or self.excluded:    # a complete grid's record omits them
            out["layout"] = self.layout
            out["positions_fitted"] = self.n_positions
            out["missing"] = [list(index) for index in self.missing]
            out["excluded"] = [e.to_dict() for e in self.excluded]
        return out
