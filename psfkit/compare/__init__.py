r"""Learned versus measured eigen-kernels: did the network learn the physics? (paper, Sec. 5.6)

The paper shows (Fig. 7) that the difference kernels ``Kv − Kbase`` and ``Kh − Kbase`` of a
trained EK-DUN look like sub-pixel displacements of the caustic spots. This module measures
those displacements and compares them with what the PSF grid of the same camera says.

Measured side (:func:`measure_modes`), from a PSF grid:

- the eigen-kernels fitted to the grid (:func:`psfkit.fitting.grid.fit.fit_eigen_grid`) with the
  learned file's basis and weight convention;
- the top PCA modes of the registered grid (:mod:`psfkit.fitting.grid.pca`);
- warp fields: the dense flow from the centre PSF to the (shift-registered, gain-matched) PSFs
  at the outermost reliable positions on the centre column (``v = ±edge, u = 0``) and centre
  row (``v = 0, u = ±edge``). For the model, ``PSF_p − PSF_0 = Σ_k ΔW_k (K_k − Kbase)``
  (``ΔW_k``: change of kernel k's weight between the centre and position p; a constant for
  source-side weights, a map for the paper's sensor-side ones). Linearising with
  ``Kv(x + D(x)) ≈ Kbase(x)`` gives ``warp_p ≈ ΔW_v · D``; the least-squares ``D`` over the
  two opposite positions is the displacement ``Kv`` (``Kh``) should show relative to
  ``Kbase`` ("predicted kernel displacement"). The paper's weights are even in ``u`` and
  ``v``, so ``Kv`` can only describe the *even* part of the change: using both sides is the
  symmetrisation. (``CompareOptions.warp_positions="all"``: every reliable position, all
  correction kernels solved jointly.)

Measured side from another kernel file (:func:`modes_from_kernel_file`; ``psfkit compare
A.npz B.npz``): B's kernels are the measured ones (a grid fit, a pairs fit, an oracle), on A's
sensor grid; a kernel file has no warps and no PCA modes, so those comparisons are absent.

Learned side: the kernels of a kernel file (after training), padded to the sensor size and
registered to the measured ``Kbase`` by one global sub-pixel shift.

Displacement maps (:func:`displacement_map`): dense optical flow (OpenCV DIS by default,
:func:`psfkit.calibration.warp.dense_flow`) from ``Kbase`` to ``Kv`` (``Kh``), on luminance, after
scaling both to the same sum on the caustic mask (gain differences are not displacements),
smoothed by a masked Gaussian (normalised convolution) and kept on the caustic mask of the
measured ``Kbase`` (:func:`psfkit.calibration.caustic.caustic_mask`).

Conventions. A displacement field ``D = (D_u, D_v)`` is ``(2, H, W)`` in pixels of the
comparison grid (the learned file's sensor grid), ``u`` = column (right), ``v`` = row (down);
it maps a point of the reference image to where it appears in the other:
``other(x + D(x)) ≈ reference(x)`` (as in :mod:`psfkit.calibration.warp`).

Metrics (per non-base kernel, e.g. ``v`` and ``h``):

- Pearson correlation of two displacement maps over the mask, for ``D_u``, ``D_v`` and both
  components together; NaN (documented, never an error) when either map has no displacement
  (RMS below ``CompareOptions.min_displacement_px``, e.g. ``Kv = Kh = Kbase``);
- end-point error ``mean |D_a − D_b|`` (px), RMS of each map, and the least-squares slope of
  ``D_a`` on ``D_b`` (1 when the amplitudes agree);
- normalised (uncentred) correlation of the difference kernels ``K_k − Kbase`` (luminance);
- principal angles (degrees) between the span of the learned kernels and (i) the span of the
  measured eigen-kernels, (ii) the span of the measured top PCA modes.

Modules: :mod:`~psfkit.compare.options` (:class:`CompareOptions`),
:mod:`~psfkit.compare.displacement` (displacement maps, the caustic mask),
:mod:`~psfkit.compare.statistics` (agreement of maps and kernels),
:mod:`~psfkit.compare.resampling` (onto the comparison grid), :mod:`~psfkit.compare.warps` and
:mod:`~psfkit.compare.measured` (the measured side), :mod:`~psfkit.compare.results` (result
classes) and :mod:`~psfkit.compare.comparison` (:func:`compare_kernels`). Writing figures, JSON
and HTML is :mod:`psfkit.report.comparison` (it draws with :mod:`psfkit.report.figures`, which
reads these results, so it sits above this package).
"""

from psfkit.compare.comparison import check_learned, compare_kernels, compare_model
from psfkit.compare.displacement import (
    DisplacementMap,
    comparison_mask,
    displacement_map,
    masked_smooth,
)
from psfkit.compare.measured import (
    MeasuredModes,
    load_grid,
    measure_modes,
    modes_from_kernel_file,
)
from psfkit.compare.options import CompareOptions
from psfkit.compare.resampling import ASPECT_TOLERANCE, check_shapes, pad_kernels, resample
from psfkit.compare.results import KernelComparison, KernelSetComparison
from psfkit.compare.statistics import map_agreement, normalized_correlation, pearson
from psfkit.compare.warps import MIN_WEIGHT_CHANGE, WARP_AXES

__all__ = [
    "ASPECT_TOLERANCE", "MIN_WEIGHT_CHANGE", "WARP_AXES", "CompareOptions", "DisplacementMap",
    "KernelComparison", "KernelSetComparison", "MeasuredModes", "check_learned",
    "check_shapes", "compare_kernels", "compare_model", "comparison_mask", "displacement_map",
    "load_grid", "map_agreement", "masked_smooth", "measure_modes", "modes_from_kernel_file",
    "normalized_correlation",
    "pad_kernels", "pearson", "resample",
]
