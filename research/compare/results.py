"""Results of a comparison: one kernel model against the measured modes
(:class:`KernelSetComparison`) and the whole comparison (:class:`KernelComparison`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psfkit.io.jsonable import jsonable
from research.compare.displacement import DisplacementMap
from research.compare.measured import MeasuredModes
from research.compare.options import CompareOptions


@dataclass
class KernelSetComparison:
    """One kernel model (``label`` "learned" or "initial") against the measured modes.

    Attributes
    ----------
    kernels : numpy.ndarray
        ``(K, C, H, W)`` on the comparison grid, registered to the measured ``Kbase``.
    displacements : dict
        Kernel name → :class:`DisplacementMap` relative to ``Kbase``.
    metrics : dict
        Kernel name → ``{"vs_measured_kernels", "vs_measured_warp"`` (:func:`map_agreement`
        or None), ``"difference_ncc"}``.
    angles_eigen_deg, angles_pca_deg : numpy.ndarray or None
        Principal angles (degrees, ascending) to the measured eigen-kernels / top PCA modes.
    global_shift_px : (float, float)
        ``(du, dv)`` of the model's ``Kbase`` relative to the measured one (undone).
    """

    label: str
    kernels: np.ndarray = field(repr=False)
    displacements: dict[str, DisplacementMap] = field(repr=False)
    metrics: dict[str, dict[str, Any]]
    angles_eigen_deg: np.ndarray | None
    angles_pca_deg: np.ndarray | None
    global_shift_px: tuple[float, float]

    def numbers(self) -> dict[str, Any]:
        """The numbers to quote, flat: per correction kernel ``k``, ``{k}_diff_ncc``,
        ``{k}_disp_corr`` (NaN without displacement) and ``{k}_epe_px``; ``angles_deg``, the
        principal angles to the reference's eigen-kernels (list)."""
        out: dict[str, Any] = {}
        for name, m in self.metrics.items():
            out[f"{name}_diff_ncc"] = float(m["difference_ncc"])
            out[f"{name}_disp_corr"] = float(m["vs_measured_kernels"]["corr"])
            out[f"{name}_epe_px"] = float(m["vs_measured_kernels"]["epe_px"])
        out["angles_deg"] = (None if self.angles_eigen_deg is None
                             else [float(a) for a in self.angles_eigen_deg])
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"label": self.label, "global_shift_px": list(self.global_shift_px),
                "displacement_rms_px": {k: d.rms() for k, d in self.displacements.items()},
                "metrics": self.metrics,
                "principal_angles_deg_vs_measured_eigen":
                    None if self.angles_eigen_deg is None else self.angles_eigen_deg.tolist(),
                "principal_angles_deg_vs_measured_pca":
                    None if self.angles_pca_deg is None else self.angles_pca_deg.tolist()}


@dataclass
class KernelComparison:
    """Result of :func:`compare_kernels`.

    Attributes
    ----------
    initial : KernelSetComparison or None
        The kernels before training (``--initial``).
    measured_displacements : dict
        Kernel name → :class:`DisplacementMap` of the measured eigen-kernel.
    measured_kernels_vs_warp : dict
        Kernel name → :func:`map_agreement` of that map with the measured warp (a ceiling for
        the learned one).
    mask : numpy.ndarray
        ``(H, W)`` bool caustic mask of the measured ``Kbase``.
    kernel_change : dict
        :func:`kernel_change_report`: ``learned_vs_measured``, ``learned_vs_initial``,
        ``support_pixels``.
    """

    learned: KernelSetComparison
    initial: KernelSetComparison | None
    measured: MeasuredModes
    measured_displacements: dict[str, DisplacementMap] = field(repr=False)
    measured_kernels_vs_warp: dict[str, dict[str, Any]]
    mask: np.ndarray = field(repr=False)
    options: CompareOptions = field(repr=False)
    notes: list[str] = field(default_factory=list)
    kernel_change: dict[str, Any] = field(default_factory=dict)

    @property
    def kernel_names(self) -> tuple[str, ...]:
        return self.measured.model.kernel_names

    def headline(self) -> dict[str, dict[str, float]]:
        """``{label: {"<name>_vs_kernels"/"_vs_warp": corr, "<name>_difference_ncc": ...}}``."""
        out = {}
        for cmp in (self.learned, self.initial):
            if cmp is None:
                continue
            row = {}
            for name, m in cmp.metrics.items():
                row[f"{name}_vs_kernels"] = m["vs_measured_kernels"]["corr"]
                if m["vs_measured_warp"] is not None:
                    row[f"{name}_vs_warp"] = m["vs_measured_warp"]["corr"]
                row[f"{name}_difference_ncc"] = m["difference_ncc"]
            out[cmp.label] = row
        return out

    def to_dict(self) -> dict[str, Any]:
        return jsonable({
            "conventions": {
                "displacement": "D = (D_u, D_v) px on the comparison grid (the kernel file's "
                                "sensor), u = column (right), v = row (down); "
                                "K_k(x + D(x)) ≈ Kbase(x)",
                "measured_warp": "flow centre PSF → edge PSF, averaged over the two opposite "
                                 "edges (paper weights are even) and divided by the kernel's "
                                 "weight there: the predicted displacement of K_k",
                "correlation": "Pearson over the caustic mask of the measured Kbase; null "
                               "(NaN) when a map has no displacement",
                "difference_ncc": "uncentred normalised correlation of K_k − Kbase "
                                  "(luminance), learned vs measured",
                "angles": "principal angles in degrees, ascending"},
            "kernel_names": list(self.kernel_names),
            "mask_pixels": int(self.mask.sum()),
            "headline": self.headline(),
            "learned": self.learned.to_dict(),
            "initial": None if self.initial is None else self.initial.to_dict(),
            "measured": self.measured.to_dict(),
            "measured_displacement_rms_px": {k: d.rms()
                                             for k, d in self.measured_displacements.items()},
            "measured_kernels_vs_warp": self.measured_kernels_vs_warp,
            "kernel_change": self.kernel_change,
            "options": {k: getattr(self.options, k) for k in (
                "flow_method", "smooth_px", "min_displacement_px", "warp_positions",
                "mask_level", "align")},
            "notes": self.notes})
