r"""Learned versus measured eigen-kernels: did the network learn the physics? (paper, Sec. 5.6)

The paper shows (Fig. 7) that the difference kernels ``Kv − Kbase`` and ``Kh − Kbase`` of a
trained EK-DUN look like sub-pixel displacements of the caustic spots. This module measures
those displacements and compares them with what the PSF grid of the same camera says.

Measured side (:func:`measure_modes`), from a PSF grid:

- the eigen-kernels fitted to the grid (:func:`psfkit.grid_fit.fit_eigen_grid`) with the
  learned file's basis and weight convention;
- the top PCA modes of the registered grid (:mod:`psfkit.pca`);
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

Learned side: the kernels of a kernel file (after training), padded to the sensor size and
registered to the measured ``Kbase`` by one global sub-pixel shift.

Displacement maps (:func:`displacement_map`): dense optical flow (OpenCV DIS by default,
:func:`psfkit.warp.dense_flow`) from ``Kbase`` to ``Kv`` (``Kh``), on luminance, after scaling
both to the same sum on the caustic mask (gain differences are not displacements), smoothed by
a masked Gaussian (normalised convolution) and kept on the caustic mask of the measured
``Kbase`` (:func:`psfkit.warp.caustic_mask`).

Conventions. A displacement field ``D = (D_u, D_v)`` is ``(2, H, W)`` in pixels of the
comparison grid (the learned file's sensor grid), ``u`` = column (right), ``v`` = row (down);
it maps a point of the reference image to where it appears in the other:
``other(x + D(x)) ≈ reference(x)`` (as in :mod:`psfkit.warp`).

Metrics (per non-base kernel, e.g. ``v`` and ``h``):

- Pearson correlation of two displacement maps over the mask, for ``D_u``, ``D_v`` and both
  components together; NaN (documented, never an error) when either map has no displacement
  (RMS below ``CompareOptions.min_displacement_px``, e.g. ``Kv = Kh = Kbase``);
- end-point error ``mean |D_a − D_b|`` (px), RMS of each map, and the least-squares slope of
  ``D_a`` on ``D_b`` (1 when the amplitudes agree);
- normalised (uncentred) correlation of the difference kernels ``K_k − Kbase`` (luminance);
- principal angles (degrees) between the span of the learned kernels and (i) the span of the
  measured eigen-kernels, (ii) the span of the measured top PCA modes.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from psfkit.alignment import GridAligner
from psfkit.eigen import position_weights
from psfkit.errors import ConfigurationError, InvalidInputError, ModelFileError
from psfkit.grid_fit import RELIABLE_OVERLAP, EigenFitOptions, GridEigenResult, fit_eigen_grid
from psfkit.io.grid import PsfGrid, read_grid
from psfkit.kernelfile import KernelModel
from psfkit.pca import principal_angles_deg
from psfkit.preprocess import PreprocessOptions, luminance
from psfkit.registration import bin_image, register_shift, shift_image
from psfkit.warp import FLOW_METHODS, caustic_mask, dense_flow
from psfkit.weights import get_basis

#: relative difference of aspect ratios (H/W) beyond which two sensor grids are not the same
ASPECT_TOLERANCE = 0.02
#: kernel names whose displacement a warp along one sensor axis predicts
WARP_AXES = {"v": "v", "h": "u"}
#: fraction of the largest Σ ΔW² below which a warp-predicted displacement is not defined
MIN_WEIGHT_CHANGE = 0.25


@dataclass(frozen=True)
class CompareOptions:
    """Options of :func:`compare_kernels`.

    Attributes
    ----------
    flow_method : str
        Dense-flow method (:func:`psfkit.warp.dense_flow`): ``"dis"`` (default), ``"farneback"``,
        ``"ilk"`` or ``"tvl1"``.
    smooth_px : float
        Standard deviation (px of the comparison grid) of the masked Gaussian applied to every
        displacement map; flows on caustics are noisy off the bright lines.
    mask_level, mask_border, mask_dilate : float, int, int
        Caustic mask (:func:`psfkit.warp.caustic_mask`): pixels within ``mask_dilate`` px of a
        pixel brighter than ``mask_level`` × the peak of the measured ``Kbase``, and
        ``mask_border`` px inside the image.
    min_displacement_px : float
        A displacement map whose RMS over the mask is below this (px) counts as "no
        displacement": its correlations are NaN.
    n_pca : int
        Number of measured PCA modes whose span the learned kernels are compared with (the
        number of kernels by default, 0 = that number).
    warp_positions : {"axes", "all"}
        Measured warps from the outermost reliable positions on each kernel's axis (``v``,
        ``h`` only; default), or from every reliable position, solved jointly for all
        correction kernels (covers more pixels with sensor-side weights, but diagonal
        positions add changes the basis cannot describe; see docs/compare.md).
    align : bool
        Register the learned ``Kbase`` to the measured one by a global sub-pixel shift first.
    fit : EigenFitOptions or None
        Options of the measured eigen-kernel fit; ``None``: the learned file's basis and
        convention, no cross-validation.
    preprocess : PreprocessOptions
        Preprocessing of the grid (dark, normalisation, saturation).
    """

    flow_method: str = "dis"
    smooth_px: float = 3.0
    mask_level: float = 0.02
    mask_border: int = 8
    mask_dilate: int = 3
    min_displacement_px: float = 0.02
    n_pca: int = 0
    warp_positions: str = "axes"
    align: bool = True
    fit: EigenFitOptions | None = None
    preprocess: PreprocessOptions = field(default_factory=PreprocessOptions)

    def __post_init__(self) -> None:
        if self.flow_method not in FLOW_METHODS:
            raise ConfigurationError(f"unknown flow method {self.flow_method!r} "
                                     f"(use {', '.join(FLOW_METHODS)})")
        if self.warp_positions not in ("all", "axes"):
            raise ConfigurationError(f"warp_positions must be 'all' or 'axes', got "
                                     f"{self.warp_positions!r}")
        if self.smooth_px < 0 or self.min_displacement_px < 0 or self.n_pca < 0:
            raise ConfigurationError("smooth_px, min_displacement_px and n_pca must be >= 0")


# --------------------------------------------------------------------------- displacement maps


@dataclass(frozen=True)
class DisplacementMap:
    """A displacement field and where it is meaningful.

    Attributes
    ----------
    field : numpy.ndarray
        ``(2, H, W)`` float32 ``(D_u, D_v)`` in px, ``other(x + D(x)) ≈ reference(x)``;
        zero outside ``mask``.
    mask : numpy.ndarray
        ``(H, W)`` bool.
    """

    field: np.ndarray = dataclasses.field(repr=False)
    mask: np.ndarray = dataclasses.field(repr=False)

    def rms(self) -> float:
        """RMS length of the displacement over the mask (px; NaN on an empty mask)."""
        if not self.mask.any():
            return float("nan")
        return float(np.sqrt(np.mean(np.sum(self.field[:, self.mask] ** 2, axis=0))))

    def scaled(self, factor: float) -> DisplacementMap:
        return DisplacementMap(field=(self.field * np.float32(factor)).astype(np.float32),
                               mask=self.mask)


def masked_smooth(values: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of ``values`` ``(..., H, W)`` using only the pixels in ``mask``
    (normalised convolution); zero outside ``mask``."""
    m = mask.astype(np.float64)
    if sigma <= 0:
        return np.where(mask, values, 0).astype(np.float32)
    weight = ndimage.gaussian_filter(m, sigma, mode="constant")
    out = np.zeros(values.shape, np.float32)
    for index in np.ndindex(values.shape[:-2]):
        smooth = ndimage.gaussian_filter(values[index] * m, sigma, mode="constant")
        out[index] = np.where(mask, smooth / np.maximum(weight, 1e-12), 0)
    return out


def displacement_map(reference: np.ndarray, other: np.ndarray, mask: np.ndarray,
                     method: str = "dis", smooth_px: float = 3.0) -> DisplacementMap:
    """Local sub-pixel displacement of ``other`` relative to ``reference`` on ``mask``.

    Parameters
    ----------
    reference, other : numpy.ndarray
        ``(H, W)`` non-negative images (e.g. kernel luminance), same frame.
    mask : numpy.ndarray
        ``(H, W)`` bool, where the displacement is meaningful (the caustic).
    method : str
        Dense-flow method (:func:`psfkit.warp.dense_flow`).
    smooth_px : float
        Sigma (px) of the masked Gaussian smoothing.

    Returns
    -------
    DisplacementMap
        ``other(x + D(x)) ≈ reference(x)``, in px.
    """
    if reference.shape != other.shape or reference.ndim != 2 or mask.shape != reference.shape:
        raise InvalidInputError("displacement_map needs two 2-D images and a mask of one shape")
    if not mask.any():
        return DisplacementMap(np.zeros((2, *reference.shape), np.float32), mask)
    ref = np.clip(reference, 0, None).astype(np.float32)
    oth = np.clip(other, 0, None).astype(np.float32)
    # gain differences (vignetting) are not displacements: match the sums on the mask
    s_ref, s_oth = float(ref[mask].sum()), float(oth[mask].sum())
    if s_ref > 0 and s_oth > 0:
        oth = oth * np.float32(s_ref / s_oth)
    flow = dense_flow(ref, oth, method)
    return DisplacementMap(masked_smooth(flow, mask, smooth_px), mask)


def pearson(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Pearson correlation of ``a`` and ``b`` (``(..., H, W)``) over ``mask`` (all leading
    components pooled); NaN when either is constant there."""
    x = a[..., mask].astype(np.float64).ravel()
    y = b[..., mask].astype(np.float64).ravel()
    if x.size < 3:
        return float("nan")
    x -= x.mean()
    y -= y.mean()
    denom = float(np.sqrt(np.sum(x * x) * np.sum(y * y)))
    return float(np.sum(x * y) / denom) if denom > 0 else float("nan")


def normalized_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Uncentred normalised correlation ``<a, b> / (|a| |b|)`` (cosine; NaN if either is 0)."""
    x = a.astype(np.float64).ravel()
    y = b.astype(np.float64).ravel()
    denom = float(np.linalg.norm(x) * np.linalg.norm(y))
    return float(np.dot(x, y) / denom) if denom > 0 else float("nan")


def map_agreement(a: DisplacementMap, b: DisplacementMap, min_displacement_px: float = 0.02
                  ) -> dict[str, float | int | str | None]:
    """How well displacement map ``a`` agrees with ``b`` on the intersection of their masks.

    Returns
    -------
    dict
        ``corr_u``, ``corr_v``, ``corr`` (Pearson, both components pooled; NaN when either map
        has no displacement), ``epe_px`` (mean end-point error), ``rms_a_px``, ``rms_b_px``,
        ``slope`` (least-squares ``a ≈ slope · b``), ``pixels`` and ``note`` (why the
        correlations are NaN, else None).
    """
    mask = a.mask & b.mask
    both = DisplacementMap(a.field, mask), DisplacementMap(b.field, mask)
    rms_a, rms_b = both[0].rms(), both[1].rms()
    out: dict[str, float | int | str | None] = {
        "pixels": int(mask.sum()), "rms_a_px": rms_a, "rms_b_px": rms_b,
        "epe_px": float(np.mean(np.hypot(*(a.field[:, mask] - b.field[:, mask]))))
        if mask.any() else float("nan"),
        "corr_u": float("nan"), "corr_v": float("nan"), "corr": float("nan"),
        "slope": float("nan"), "note": None}
    if not mask.any():
        out["note"] = "no common pixels"
        return out
    if not (rms_a >= min_displacement_px and rms_b >= min_displacement_px):
        out["note"] = (f"no displacement (RMS {rms_a:.3g} / {rms_b:.3g} px below "
                       f"{min_displacement_px} px): correlation undefined")
        return out
    out["corr_u"] = pearson(a.field[0], b.field[0], mask)
    out["corr_v"] = pearson(a.field[1], b.field[1], mask)
    out["corr"] = pearson(a.field, b.field, mask)
    fa, fb = a.field[:, mask].astype(np.float64), b.field[:, mask].astype(np.float64)
    out["slope"] = float(np.sum(fa * fb) / max(np.sum(fb * fb), 1e-300))
    return out


# --------------------------------------------------------------------------- resampling


def check_shapes(sensor_shape: tuple[int, int], grid_shape: tuple[int, int], where: str
                 ) -> None:
    """Refuse two sensor grids whose aspect ratios differ (they cannot be the same sensor)."""
    ratio_a = sensor_shape[0] / sensor_shape[1]
    ratio_b = grid_shape[0] / grid_shape[1]
    if abs(ratio_a - ratio_b) > ASPECT_TOLERANCE * ratio_b:
        raise InvalidInputError(
            f"{where}: sensor {sensor_shape[0]}x{sensor_shape[1]} of the kernel file and PSFs "
            f"{grid_shape[0]}x{grid_shape[1]} of the grid have different aspect ratios; they "
            "cannot be the same camera at two resolutions")


def resample(images: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resample ``(..., H, W)`` images to ``shape``: block averages for an integer factor,
    area interpolation to shrink, cubic to enlarge (pixel values keep their density)."""
    h, w = images.shape[-2:]
    if (h, w) == tuple(shape):
        return images.astype(np.float32, copy=False)
    flat = images.reshape(-1, h, w).astype(np.float32)
    fv, fu = h / shape[0], w / shape[1]
    out = np.empty((len(flat), *shape), np.float32)
    integer = fv == fu and float(fv).is_integer() and h % shape[0] == 0 and w % shape[1] == 0
    for i, img in enumerate(flat):
        if integer:
            out[i] = bin_image(img, int(fv)) / fv**2
        else:
            interp = cv2.INTER_AREA if fv > 1 else cv2.INTER_CUBIC
            out[i] = cv2.resize(img, (shape[1], shape[0]), interpolation=interp)
    return out.reshape(*images.shape[:-2], *shape)


def pad_kernels(kernels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(K, C, Hk, Wk)`` kernels zero-padded to ``shape`` keeping the origin at the centre
    (``(Hk//2, Wk//2)`` lands on ``(H//2, W//2)``)."""
    hk, wk = kernels.shape[-2:]
    h, w = shape
    if (hk, wk) == (h, w):
        return kernels
    out = np.zeros((*kernels.shape[:-2], h, w), np.float32)
    r0, c0 = h // 2 - hk // 2, w // 2 - wk // 2
    out[..., r0:r0 + hk, c0:c0 + wk] = kernels
    return out


# --------------------------------------------------------------------------- measured side


@dataclass
class MeasuredModes:
    """What a PSF grid says about the eigen-kernels, on the comparison grid.

    Attributes
    ----------
    model : KernelModel
        Eigen-kernels fitted to the grid, resampled to ``sensor_shape``.
    sensor_shape : (int, int)
        The comparison grid ``(H, W)`` (the learned file's sensor size).
    warps : dict
        Kernel name (``"v"``, ``"h"``) → :class:`DisplacementMap`: the displacement of that
        kernel relative to ``Kbase`` predicted by the measured warps (see the module
        docstring).
    warp_positions : dict
        Kernel name (or ``"all"``) → list of ``{"row", "col", "shift_px",
        "mean_weight_change", "overlap", "warp_rms_px"}`` of the positions used.
    pca_components : numpy.ndarray or None
        ``(r, C, h, w)`` top uncentred PCA modes on the fit's binned working grid.
    pca_region : numpy.ndarray or None
        ``(h, w)`` bool, pixels the PCA used.
    fit : GridEigenResult
    notes : list of str
        What was resampled, skipped or approximated.
    """

    model: KernelModel
    sensor_shape: tuple[int, int]
    warps: dict[str, DisplacementMap]
    warp_positions: dict[str, list[dict[str, Any]]]
    pca_components: np.ndarray | None
    pca_region: np.ndarray | None
    fit: GridEigenResult = field(repr=False)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"grid": self.fit.grid_root, "grid_shape": list(self.fit.grid_shape),
                "image_shape": list(self.fit.image_shape),
                "comparison_shape": list(self.sensor_shape),
                "basis": self.model.basis, "convention": self.model.convention,
                "warp_positions": self.warp_positions,
                "warp_rms_px": {k: w.rms() for k, w in self.warps.items()},
                "pca_modes": None if self.pca_components is None
                else len(self.pca_components),
                "fit": self.fit.summary(), "notes": self.notes}


def _axis_positions(grid: PsfGrid, axis: str) -> list[list[tuple[int, int]]]:
    """Grid indices from the outermost inward on both sides of the centre, along ``axis``
    (``"v"``: the centre column, ``"u"``: the centre row)."""
    cr, cc = grid.require_center()
    n_rows, n_cols = grid.grid_shape
    if axis == "v":
        return [[(r, cc) for r in range(0, cr)], [(r, cc) for r in range(n_rows - 1, cr, -1)]]
    return [[(cr, c) for c in range(0, cc)], [(cr, c) for c in range(n_cols - 1, cc, -1)]]


def _weight_change(basis_name: str, convention: str, kernel: int,
                   image_shape: tuple[int, int], shift: tuple[float, float],
                   sensor_shape: tuple[int, int]) -> np.ndarray:
    """``ΔW(x) = W_k(position) − W_k(centre)`` of kernel ``kernel`` in the aligned frame,
    ``(H, W)`` on the comparison grid (constant for source-side weights)."""
    basis = get_basis(basis_name)
    edge = position_weights(basis, image_shape, shift, convention)[kernel]
    centre = position_weights(basis, image_shape, (0.0, 0.0), convention)[kernel]
    change = np.broadcast_to(edge - centre, image_shape).astype(np.float32)
    return resample(change, sensor_shape)


def _measured_warp(aligner: GridAligner, name: str, basis_name: str, convention: str,
                   image_shape: tuple[int, int], sensor_shape: tuple[int, int],
                   mask: np.ndarray, options: CompareOptions
                   ) -> tuple[DisplacementMap | None, list[dict[str, Any]], list[str]]:
    """Predicted displacement of kernel ``name`` (``"v"``/``"h"``) from the warps of the
    outermost reliable PSFs on both sides of the centre along its axis.

    With ``PSF_p − PSF_0 = Σ_k ΔW_k (K_k − Kbase)`` (exact for the model; ``ΔW_k`` the change
    of kernel k's weight between the centre and position p, constant for source-side weights,
    a map for sensor-side ones) and ``K_k(x + D(x)) ≈ Kbase(x)`` linearised, the warp of
    position p is ``ΔW_k · D``. ``D`` is the least-squares solution over the two sides,
    ``Σ ΔW·warp / Σ ΔW²`` (the average of ``warp / w`` for source-side weights), kept where
    ``Σ ΔW²`` is at least :data:`MIN_WEIGHT_CHANGE` of its maximum (elsewhere the warp says
    little about ``D`` and dividing by a small ``ΔW`` amplifies the flow's noise).
    """
    grid = aligner.grid
    k = get_basis(basis_name).kernel_names.index(name)
    reference = resample(aligner.reference_luminance, sensor_shape)
    num = np.zeros((2, *sensor_shape), np.float64)
    den = np.zeros(sensor_shape, np.float64)
    used, notes = [], []
    for side in _axis_positions(grid, WARP_AXES[name]):
        for row, col in side:               # outermost first: the largest, clearest warp
            aligned = aligner.align(grid.position(row, col))
            if aligned.overlap < RELIABLE_OVERLAP:
                continue
            change = _weight_change(basis_name, convention, k, image_shape, aligned.shift,
                                    sensor_shape)
            # the flow is unreliable within a patch of the edge of the data
            valid = ndimage.binary_erosion(
                resample(aligned.valid.astype(np.float32), sensor_shape) > 0.999,
                iterations=max(options.mask_border, 1), border_value=0)
            here = mask & valid
            disp = displacement_map(reference, resample(aligned.luminance, sensor_shape), here,
                                    options.flow_method, options.smooth_px)
            num += disp.field * (change * here)
            den += change**2 * here
            used.append({"row": row, "col": col, "shift_px": list(aligned.shift),
                         "mean_weight_change": float(np.mean(change[here])) if here.any()
                         else float("nan"),
                         "overlap": aligned.overlap, "warp_rms_px": disp.rms()})
            break
    if not used:
        notes.append(f"warp {name}: no position on that axis overlaps the centre PSF on "
                     f">= {100 * RELIABLE_OVERLAP:.0f}% of the sensor; no measured warp")
        return None, used, notes
    if len(used) == 1:
        notes.append(f"warp {name}: only one side of the axis is usable; not symmetrised")
    defined = (den >= MIN_WEIGHT_CHANGE * den.max()) & (den > 0)
    field_ = np.where(defined, num / np.maximum(den, 1e-12), 0).astype(np.float32)
    return DisplacementMap(field_, defined), used, notes


def _measured_warps_joint(aligner: GridAligner, basis_name: str, convention: str,
                          image_shape: tuple[int, int], sensor_shape: tuple[int, int],
                          mask: np.ndarray, options: CompareOptions
                          ) -> tuple[dict[str, DisplacementMap], list[dict[str, Any]],
                                     list[str]]:
    """Predicted displacements of every correction kernel from the warps of all reliable
    positions at once.

    At every pixel ``x``, ``warp_p(x) ≈ Σ_k ΔW_{k,p}(x) · D_k(x)`` over the positions p that
    overlap the centre PSF on at least half the sensor; the ``D_k`` are the per-pixel
    least-squares solution (kept where the smallest eigenvalue of the per-pixel normal matrix
    is at least :data:`MIN_WEIGHT_CHANGE` of its largest value over the image). With the
    paper's even weights, positions on opposite sides enter with the same ``ΔW``: the fit
    averages them (the symmetrisation).
    """
    grid = aligner.grid
    basis = get_basis(basis_name)
    names = basis.kernel_names[1:]
    n = len(names)
    reference = resample(aligner.reference_luminance, sensor_shape)
    gram = np.zeros((*sensor_shape, n, n), np.float64)
    rhs = np.zeros((*sensor_shape, n, 2), np.float64)
    used, notes = [], []
    centre = grid.require_center()
    for pos in grid.positions:
        if (pos.row, pos.col) == centre:
            continue
        aligned = aligner.align(pos)
        if aligned.overlap < RELIABLE_OVERLAP:
            continue
        changes = np.stack([_weight_change(basis_name, convention, k, image_shape,
                                           aligned.shift, sensor_shape)
                            for k in range(1, n + 1)])                       # (n, H, W)
        # the flow is unreliable within a patch of the edge of the data
        valid = ndimage.binary_erosion(
            resample(aligned.valid.astype(np.float32), sensor_shape) > 0.999,
            iterations=max(options.mask_border, 1), border_value=0)
        here = mask & valid
        if not here.any():
            continue
        disp = displacement_map(reference, resample(aligned.luminance, sensor_shape), here,
                                options.flow_method, options.smooth_px)
        weighted = changes * here                                            # (n, H, W)
        gram += np.einsum("ihw,jhw->hwij", weighted, changes)
        rhs += np.einsum("ihw,chw->hwic", weighted, disp.field)
        used.append({"row": pos.row, "col": pos.col, "shift_px": list(aligned.shift),
                     "overlap": aligned.overlap, "warp_rms_px": disp.rms(),
                     "mean_weight_change": {name: float(np.mean(changes[i][here]))
                                            for i, name in enumerate(names)}})
    if not used:
        notes.append(f"no position overlaps the centre PSF on >= {100 * RELIABLE_OVERLAP:.0f}% "
                     "of the sensor; no measured warp")
        return {}, used, notes
    smallest = np.linalg.eigvalsh(gram)[..., 0]
    defined = smallest >= MIN_WEIGHT_CHANGE * smallest.max()
    if not defined.any() or smallest.max() <= 0:
        notes.append("the grid's positions do not determine the warp of every correction "
                     "kernel (too few positions off the axes?); no measured warp")
        return {}, used, notes
    solution = np.zeros_like(rhs)
    solution[defined] = np.linalg.solve(gram[defined], rhs[defined])          # (m, n, 2)
    warps = {name: DisplacementMap(np.moveaxis(solution[:, :, i, :], -1, 0).astype(np.float32)
                                   * defined, defined)
             for i, name in enumerate(names)}
    return warps, used, notes


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
    measured : PsfGrid or path
        The PSF grid of the camera.
    basis, convention : str
        Weight basis and convention of the fitted eigen-kernels (those of the learned file).
    sensor_shape : (int, int)
        The comparison grid ``(H, W)``; the grid's PSFs are resampled to it when their size
        differs (same aspect ratio required).
    options : CompareOptions, optional

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
    model = KernelModel(kernels=resample(fitted.kernels, tuple(sensor_shape)),
                        basis=fitted.basis, convention=fitted.convention,
                        sensor_shape=tuple(sensor_shape), channels=fitted.channels,
                        normalization=fitted.normalization, provenance=fitted.provenance)
    base_lum = luminance(model.kernels[0])
    mask = comparison_mask(base_lum, options)
    aligner = GridAligner(grid, fit_options.preprocess, fit_options.upsample)
    warps, positions = {}, {}
    if options.warp_positions == "all":
        warps, used, more = _measured_warps_joint(aligner, basis, convention, (h, w),
                                                  tuple(sensor_shape), mask, options)
        notes.extend(more)
        positions = {"all": used}
    for name in get_basis(basis).kernel_names[1:] if options.warp_positions == "axes" else ():
        if name not in WARP_AXES:
            notes.append(f"kernel {name!r}: no single-axis warp predicts it; kernel and PCA "
                         "comparisons only")
            continue
        warp, used, more = _measured_warp(aligner, name, basis, convention, (h, w),
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
                         pca_region=None if pca is None else pca.region, fit=fit, notes=notes)


def comparison_mask(base_luminance: np.ndarray, options: CompareOptions) -> np.ndarray:
    """Caustic mask of the measured ``Kbase`` luminance ``(H, W)`` (see
    :func:`psfkit.warp.caustic_mask`)."""
    return caustic_mask(base_luminance, np.ones(base_luminance.shape, bool), options.mask_level,
                        options.mask_border, options.mask_dilate)


# --------------------------------------------------------------------------- comparison


@dataclass
class KernelSetComparison:
    """One kernel model (learned, or its initial value) against the measured modes.

    Attributes
    ----------
    label : str
        ``"learned"`` or ``"initial"``.
    kernels : numpy.ndarray
        ``(K, C, H, W)`` the model's kernels on the comparison grid, registered to the
        measured ``Kbase``.
    displacements : dict
        Kernel name → :class:`DisplacementMap` of that kernel relative to ``Kbase``.
    metrics : dict
        Kernel name → ``{"vs_measured_kernels": map_agreement, "vs_measured_warp":
        map_agreement or None, "difference_ncc": float}``.
    angles_eigen_deg, angles_pca_deg : numpy.ndarray or None
        Principal angles (degrees, ascending) between the span of the kernels and the span of
        the measured eigen-kernels / top PCA modes.
    global_shift_px : (float, float)
        ``(du, dv)`` by which the model's ``Kbase`` was displaced relative to the measured one
        (undone before comparing).
    """

    label: str
    kernels: np.ndarray = field(repr=False)
    displacements: dict[str, DisplacementMap] = field(repr=False)
    metrics: dict[str, dict[str, Any]]
    angles_eigen_deg: np.ndarray | None
    angles_pca_deg: np.ndarray | None
    global_shift_px: tuple[float, float]

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
    learned : KernelSetComparison
    initial : KernelSetComparison or None
        The same numbers for the kernels before training (``--initial``).
    measured : MeasuredModes
    measured_displacements : dict
        Kernel name → :class:`DisplacementMap` of the measured eigen-kernel relative to the
        measured ``Kbase``.
    measured_kernels_vs_warp : dict
        Kernel name → :func:`map_agreement` of the measured eigen-kernel displacement with the
        measured warp (how far the fit itself follows the warp: a ceiling for the learned one).
    mask : numpy.ndarray
        ``(H, W)`` bool caustic mask of the measured ``Kbase``.
    options : CompareOptions
    notes : list of str
    """

    learned: KernelSetComparison
    initial: KernelSetComparison | None
    measured: MeasuredModes
    measured_displacements: dict[str, DisplacementMap] = field(repr=False)
    measured_kernels_vs_warp: dict[str, dict[str, Any]]
    mask: np.ndarray = field(repr=False)
    options: CompareOptions = field(repr=False)
    notes: list[str] = field(default_factory=list)

    @property
    def kernel_names(self) -> tuple[str, ...]:
        return self.measured.model.kernel_names

    def headline(self) -> dict[str, dict[str, float]]:
        """``{label: {"<name>_vs_warp": corr, "<name>_vs_kernels": corr, ...}}`` for the
        learned (and initial) kernels: the numbers to quote."""
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
        from psfkit.report import jsonable

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
            "options": {"flow_method": self.options.flow_method,
                        "smooth_px": self.options.smooth_px,
                        "min_displacement_px": self.options.min_displacement_px,
                        "warp_positions": self.options.warp_positions,
                        "mask_level": self.options.mask_level, "align": self.options.align},
            "notes": self.notes})


def _kernel_displacements(lum: np.ndarray, names: tuple[str, ...], mask: np.ndarray,
                          options: CompareOptions) -> dict[str, DisplacementMap]:
    return {name: displacement_map(lum[0], lum[k], mask, options.flow_method, options.smooth_px)
            for k, name in enumerate(names) if k > 0}


def _prepare_learned(learned: KernelModel, measured: MeasuredModes, options: CompareOptions,
                     where: str) -> tuple[np.ndarray, tuple[float, float]]:
    """Learned kernels padded to the sensor and registered to the measured ``Kbase``."""
    if learned.basis != measured.model.basis or learned.convention != measured.model.convention:
        raise ModelFileError(f"{where}: basis/convention {learned.basis}/{learned.convention} "
                             f"differ from the measured fit's {measured.model.basis}/"
                             f"{measured.model.convention}")
    if tuple(learned.sensor_shape) != tuple(measured.sensor_shape):
        raise ModelFileError(f"{where}: sensor {list(learned.sensor_shape)} differs from the "
                             f"comparison grid {list(measured.sensor_shape)}")
    kernels = pad_kernels(learned.kernels, tuple(measured.sensor_shape))
    if kernels.shape[1] != measured.model.kernels.shape[1]:
        raise ModelFileError(f"{where}: {kernels.shape[1]} channel(s) but the grid has "
                             f"{measured.model.kernels.shape[1]}")
    shift = (0.0, 0.0)
    if options.align:
        shift = register_shift(luminance(measured.model.kernels[0]), luminance(kernels[0]))
        if abs(shift[0]) > 0.005 or abs(shift[1]) > 0.005:
            kernels = shift_image(kernels.reshape(-1, *kernels.shape[-2:]), shift)[0].reshape(
                kernels.shape)
    return kernels, (float(shift[0]), float(shift[1]))


def _angles(kernels: np.ndarray, measured: MeasuredModes, n_pca: int
            ) -> tuple[np.ndarray, np.ndarray | None]:
    eigen = principal_angles_deg(kernels, measured.model.kernels)
    if measured.pca_components is None or measured.pca_region is None:
        return eigen, None
    n = min(n_pca or len(kernels), len(measured.pca_components))
    region = measured.pca_region
    working = resample(kernels, region.shape)
    pca = principal_angles_deg(working[:, :, region], measured.pca_components[:n][:, :, region])
    return eigen, pca


def compare_model(model: KernelModel, measured: MeasuredModes, label: str = "learned",
                  options: CompareOptions | None = None, where: str = "learned kernels"
                  ) -> KernelSetComparison:
    """Compare one kernel model with measured modes (see the module docstring).

    Raises
    ------
    ModelFileError
        Basis, convention, sensor size or channels differ from the measured fit's.
    """
    options = options or CompareOptions()
    kernels, shift = _prepare_learned(model, measured, options, where)
    names = measured.model.kernel_names
    lum = np.stack([luminance(k) for k in kernels])
    meas_lum = np.stack([luminance(k) for k in measured.model.kernels])
    mask = comparison_mask(meas_lum[0], options)
    disp = _kernel_displacements(lum, names, mask, options)
    meas_disp = _kernel_displacements(meas_lum, names, mask, options)
    metrics = {}
    for k, name in enumerate(names):
        if k == 0:
            continue
        warp = measured.warps.get(name)
        metrics[name] = {
            "vs_measured_kernels": map_agreement(disp[name], meas_disp[name],
                                                 options.min_displacement_px),
            "vs_measured_warp": None if warp is None else map_agreement(
                disp[name], warp, options.min_displacement_px),
            "difference_ncc": normalized_correlation(lum[k] - lum[0], meas_lum[k] - meas_lum[0]),
        }
    eigen, pca = _angles(kernels, measured, options.n_pca)
    return KernelSetComparison(label=label, kernels=kernels, displacements=disp,
                               metrics=metrics, angles_eigen_deg=eigen, angles_pca_deg=pca,
                               global_shift_px=shift)


def _as_model(value: KernelModel | str | os.PathLike) -> KernelModel:
    from psfkit.kernelfile import load_kernels

    if isinstance(value, KernelModel):
        return value
    return load_kernels(value)


def check_learned(model: KernelModel, where: str) -> None:
    """Refuse a kernel model without correction kernels (nothing to compare)."""
    if len(model.kernels) < 2:
        raise ModelFileError(f"{where}: basis {model.basis!r} has a single kernel; the "
                             "comparison needs Kbase and correction kernels (e.g. basis "
                             "'paper': Kbase, Kv, Kh)")


def compare_kernels(learned: KernelModel | str | os.PathLike,
                    measured: PsfGrid | str | os.PathLike | MeasuredModes,
                    initial: KernelModel | str | os.PathLike | None = None,
                    options: CompareOptions | None = None, progress: bool = False
                    ) -> KernelComparison:
    """Compare learned eigen-kernels with the measured modes of the same camera.

    Parameters
    ----------
    learned : KernelModel or path
        The trained model's kernels (a kernel file with at least two kernels).
    measured : PsfGrid, path or MeasuredModes
        The camera's PSF grid (or modes already measured by :func:`measure_modes` on the
        learned file's sensor grid, to compare several models without refitting).
    initial : KernelModel or path, optional
        The kernels before training: the same numbers are reported for them.
    options : CompareOptions, optional
    progress : bool
        Progress bar for the grid fit.

    Returns
    -------
    KernelComparison

    Raises
    ------
    ModelFileError
        A kernel file is unreadable, of the wrong version, has one kernel, or its basis,
        convention or sensor size differs from the other's.
    GridFormatError, InvalidInputError
        Not a grid, or a grid whose PSFs cannot be brought to the kernel file's sensor size.
    """
    options = options or CompareOptions()
    learned_model = _as_model(learned)
    where = str(learned) if not isinstance(learned, KernelModel) else "learned kernels"
    check_learned(learned_model, where)
    initial_model = None
    if initial is not None:
        initial_model = _as_model(initial)
        iw = str(initial) if not isinstance(initial, KernelModel) else "initial kernels"
        check_learned(initial_model, iw)
        for attr in ("basis", "convention", "sensor_shape"):
            if getattr(initial_model, attr) != getattr(learned_model, attr):
                raise ModelFileError(f"{iw}: {attr} {getattr(initial_model, attr)!r} differs "
                                     f"from the learned file's {getattr(learned_model, attr)!r}")
    if isinstance(measured, MeasuredModes):
        modes = measured
    else:
        modes = measure_modes(measured, learned_model.basis, learned_model.convention,
                              tuple(learned_model.sensor_shape), options, progress)
    result_learned = compare_model(learned_model, modes, "learned", options, where)
    result_initial = None if initial_model is None else compare_model(
        initial_model, modes, "initial", options, "initial kernels")
    meas_lum = np.stack([luminance(k) for k in modes.model.kernels])
    mask = comparison_mask(meas_lum[0], options)
    meas_disp = _kernel_displacements(meas_lum, modes.model.kernel_names, mask, options)
    vs_warp = {name: map_agreement(meas_disp[name], warp, options.min_displacement_px)
               for name, warp in modes.warps.items() if name in meas_disp}
    notes = list(modes.notes)
    if learned_model.kernels.shape[-2:] != tuple(learned_model.sensor_shape):
        notes.append(f"learned kernels {learned_model.kernels.shape[-2]}x"
                     f"{learned_model.kernels.shape[-1]} zero-padded to the sensor size")
    return KernelComparison(learned=result_learned, initial=result_initial, measured=modes,
                            measured_displacements=meas_disp, measured_kernels_vs_warp=vs_warp,
                            mask=mask, options=options, notes=notes)
