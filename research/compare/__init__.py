"""Learned versus measured eigen-kernels: did the network learn the physics? (paper, Sec. 5.6)

The difference kernels ``Kv − Kbase``, ``Kh − Kbase`` of a trained EK-DUN look like sub-pixel
displacements of the caustic spots (Fig. 7). :func:`compare_kernels` measures them and compares
them with the camera's PSF grid (:func:`measure_modes`: fitted eigen-kernels, top PCA modes,
warp-predicted displacements) or another kernel file (:func:`modes_from_kernel_file`): Pearson
correlation, end-point error, RMS and slope of the displacement maps (:func:`map_agreement`),
the normalised correlation of ``K_k − Kbase`` and principal angles between the spans.
Conventions: :mod:`~research.compare.displacement`; figures, JSON and HTML:
:mod:`research.compare.report`.
"""

from research.compare.comparison import check_learned, compare_kernels, compare_model
from research.compare.displacement import (
    DisplacementMap,
    comparison_mask,
    displacement_map,
    masked_smooth,
)
from research.compare.measured import (
    MeasuredModes,
    load_grid,
    measure_modes,
    modes_from_kernel_file,
)
from research.compare.options import CompareOptions
from research.compare.resampling import ASPECT_TOLERANCE, check_shapes, pad_kernels, resample
from research.compare.results import KernelComparison, KernelSetComparison
from research.compare.statistics import map_agreement, normalized_correlation, pearson
from research.compare.warps import MIN_WEIGHT_CHANGE, WARP_AXES

__all__ = [
    "ASPECT_TOLERANCE", "MIN_WEIGHT_CHANGE", "WARP_AXES", "CompareOptions", "DisplacementMap",
    "KernelComparison", "KernelSetComparison", "MeasuredModes", "check_learned",
    "check_shapes", "compare_kernels", "compare_model", "comparison_mask", "displacement_map",
    "load_grid", "map_agreement", "masked_smooth", "measure_modes", "modes_from_kernel_file",
    "normalized_correlation", "pad_kernels", "pearson", "resample",
]
