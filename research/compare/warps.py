"""Measured warps: the displacement of each correction kernel relative to ``Kbase`` that the
dense flow between the centre PSF and off-axis PSFs of a grid predicts.

For the model, ``PSF_p − PSF_0 = Σ_k ΔW_k (K_k − Kbase)`` (``ΔW_k``: change of kernel k's
weight between the centre and position p; a constant for source-side weights, a map for the
paper's sensor-side ones). Linearising with ``Kv(x + D(x)) ≈ Kbase(x)`` gives
``warp_p ≈ ΔW_v · D``; the least-squares ``D`` over the two opposite positions is the
displacement ``Kv`` (``Kh``) should show relative to ``Kbase``. The paper's weights are even in
``u`` and ``v``, so ``Kv`` can only describe the *even* part of the change: using both sides is
the symmetrisation. (``CompareOptions.warp_positions="all"``: every reliable position, all
correction kernels solved jointly, :func:`measured_warps_joint`.)
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage

from psfkit.calibration.alignment import RELIABLE_OVERLAP, AlignedPsf, GridAligner
from psfkit.fitting.grid.design import position_weights
from psfkit.forward.weights import get_basis
from psfkit.io.grid import PsfGrid
from research.compare.displacement import DisplacementMap, displacement_map
from research.compare.options import CompareOptions
from research.compare.resampling import resample

#: kernel names whose displacement a warp along one sensor axis predicts
WARP_AXES = {"v": "v", "h": "u"}
#: fraction of the largest Σ ΔW² below which a warp-predicted displacement is not defined
MIN_WEIGHT_CHANGE = 0.25


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


def _flow(aligned: AlignedPsf, reference: np.ndarray, mask: np.ndarray,
          sensor_shape: tuple[int, int], options: CompareOptions
          ) -> tuple[np.ndarray, DisplacementMap]:
    """The pixels of ``mask`` where ``aligned`` holds data, away from its edge, on the
    comparison grid, and its displacement map there."""
    # the flow is unreliable within a patch of the edge of the data
    valid = ndimage.binary_erosion(
        resample(aligned.valid.astype(np.float32), sensor_shape) > 0.999,
        iterations=max(options.mask_border, 1), border_value=0)
    here = mask & valid
    return here, displacement_map(reference, resample(aligned.luminance, sensor_shape), here,
                                  options.flow_method, options.smooth_px)


def measured_warp(aligner: GridAligner, name: str, basis_name: str, convention: str,
                   image_shape: tuple[int, int], sensor_shape: tuple[int, int],
                   mask: np.ndarray, options: CompareOptions
                   ) -> tuple[DisplacementMap | None, list[dict[str, Any]], list[str]]:
    """Predicted displacement of kernel ``name`` (``"v"``/``"h"``) from the warps of the
    outermost reliable PSFs on both sides of the centre along its axis (module docstring):
    ``D = Σ ΔW·warp / Σ ΔW²``, kept where ``Σ ΔW²`` is at least :data:`MIN_WEIGHT_CHANGE` of
    its maximum (elsewhere a small ``ΔW`` would amplify the flow's noise).
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
            if aligned.support_overlap < RELIABLE_OVERLAP:
                continue
            change = _weight_change(basis_name, convention, k, image_shape, aligned.shift,
                                    sensor_shape)
            here, disp = _flow(aligned, reference, mask, sensor_shape, options)
            num += disp.field * (change * here)
            den += change**2 * here
            used.append({"row": row, "col": col, "shift_px": list(aligned.shift),
                         "mean_weight_change": float(np.mean(change[here])) if here.any()
                         else float("nan"),
                         "overlap": aligned.overlap, "warp_rms_px": disp.rms()})
            break
    if not used:
        notes.append(f"warp {name}: no position on that axis has >= "
                     f"{100 * RELIABLE_OVERLAP:.0f}% of the centre PSF's light in its overlap; "
                     "no measured warp")
        return None, used, notes
    if len(used) == 1:
        notes.append(f"warp {name}: only one side of the axis is usable; not symmetrised")
    defined = (den >= MIN_WEIGHT_CHANGE * den.max()) & (den > 0)
    field_ = np.where(defined, num / np.maximum(den, 1e-12), 0).astype(np.float32)
    return DisplacementMap(field_, defined), used, notes


def measured_warps_joint(aligner: GridAligner, basis_name: str, convention: str,
                          image_shape: tuple[int, int], sensor_shape: tuple[int, int],
                          mask: np.ndarray, options: CompareOptions
                          ) -> tuple[dict[str, DisplacementMap], list[dict[str, Any]],
                                     list[str]]:
    """Predicted displacements of every correction kernel from all reliable positions at once:
    per pixel, the least-squares ``D_k`` of ``warp_p(x) ≈ Σ_k ΔW_{k,p}(x) · D_k(x)``, kept where
    the normal matrix's smallest eigenvalue is at least :data:`MIN_WEIGHT_CHANGE` of its
    largest over the image.
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
        if aligned.support_overlap < RELIABLE_OVERLAP:
            continue
        changes = np.stack([_weight_change(basis_name, convention, k, image_shape,
                                           aligned.shift, sensor_shape)
                            for k in range(1, n + 1)])                       # (n, H, W)
        here, disp = _flow(aligned, reference, mask, sensor_shape, options)
        if not here.any():
            continue
        weighted = changes * here                                            # (n, H, W)
        gram += np.einsum("ihw,jhw->hwij", weighted, changes)
        rhs += np.einsum("ihw,chw->hwic", weighted, disp.field)
        used.append({"row": pos.row, "col": pos.col, "shift_px": list(aligned.shift),
                     "overlap": aligned.overlap, "warp_rms_px": disp.rms(),
                     "mean_weight_change": {name: float(np.mean(changes[i][here]))
                                            for i, name in enumerate(names)}})
    if not used:
        notes.append(f"no position has >= {100 * RELIABLE_OVERLAP:.0f}% of the centre PSF's "
                     "light in its overlap; no measured warp")
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
