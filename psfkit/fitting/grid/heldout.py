r"""Held-out test of a field dependence of the PSF shape (the verdict's evidence).

Every model writes the aligned, gain-compensated PSF of position ``p`` as
:math:`a_p(v) = \sum_k w_{pk} K_k(v)` with position-only weights, fitted by least squares per
kernel pixel. The null ``si+sampling`` is one PSF plus four kernels weighted by the first
harmonics of the sub-pixel phase ``φ = s − round(s)`` (``sin 2πφ``, ``cos 2πφ − 1`` per axis:
aligning an aliased PSF changes it with φ, which a regular grid changes steadily);
``si+sampling+<basis>`` adds an eigen-kernel basis' field weights (:data:`FIELD_BASES`).
Positions are held out as in :func:`~psfkit.fitting.grid.stack_fit.cross_validate_positions`;
:func:`judge` runs both cross-validations and decides the verdict.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage

from psfkit.calibration.registration import shift_image
from psfkit.fitting.grid.design import source_weights
from psfkit.fitting.grid.eigen import _solve_spd
from psfkit.fitting.grid.stack_fit import (
    CENTRE_ONLY,
    CrossValidation,
    cross_validate_positions,
    fold_groups,
)
from psfkit.fitting.grid.working_stack import WorkingStack
from psfkit.fitting.verdict import HeldOutErrors, Verdict, decide
from psfkit.forward.kernelfile import CONVENTIONS
from psfkit.forward.weights import get_basis
from psfkit.numerics.significance import Estimate

#: Field bases tested against the null model.
FIELD_BASES = ("paper", "paper+odd", "poly:2")
NULL_MODEL = "si+sampling"
#: Longest side (px) of the working copy the verdict of ``psfkit report`` is computed on (as
#: ``psfkit fit-eigen``'s, :class:`psfkit.fitting.grid.options.EigenFitOptions`).
VERDICT_WORKING_SIZE = 256
#: Ridge on the correction kernels, relative to each pixel's mean diagonal (as
#: :data:`psfkit.fitting.grid.eigen.DEFAULT_RIDGE`).
RIDGE = 1e-4


def sampling_weights(shifts_px: np.ndarray) -> np.ndarray:
    """``(P, 4)`` first harmonics of each shift's sub-pixel phase (full-resolution px)."""
    phase = 2 * np.pi * (shifts_px - np.round(shifts_px))
    return np.column_stack([np.sin(phase), np.cos(phase) - 1.0])


def _sums(mask: np.ndarray, images: np.ndarray, design: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel Gram ``(K, K, N)`` and right-hand sides ``(K, C, N)`` of the listed positions
    (``mask`` ``(P, N)``, ``images`` ``(P, C, N)``, ``design`` ``(P, K)``)."""
    gram = np.einsum("pn,pk,pl->kln", mask, design, design, optimize=True)
    rhs = np.einsum("pn,pk,pcn->kcn", mask, design, images, optimize=True)
    return gram, rhs


def solve_position_weights(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Kernels ``(K, C, N)`` of the per-pixel systems; a ridge of :data:`RIDGE` (relative to each
    pixel's mean diagonal) pulls the corrections (weights after the first) towards 0."""
    k = gram.shape[0]
    scale = np.einsum("kkn->n", gram) / k + 1e-300
    prior = np.diag([1e-12] + [RIDGE] * (k - 1))
    system = gram / scale + prior[:, :, None]
    return _solve_spd(system, rhs / scale)


def held_out_models(stack: WorkingStack, center_row: int, sensor_shape: tuple[int, int],
                    folds: int = 9, seed: int = 0,
                    bases: tuple[str, ...] = FIELD_BASES) -> HeldOutErrors | None:
    """Per-position held-out squared errors of the null and each field model on the
    gain-compensated working stack; ``None`` when too few positions determine the null model.

    All models' normal equations are blocks of one design's, summed once over all positions and
    once per held-out group (training = total − group).
    """
    n = len(stack.images)
    groups = fold_groups(n, center_row, folds, seed)
    training = n - max((len(g) for g in groups), default=n)
    shifts = stack.shifts * stack.factor
    null = np.column_stack([np.ones(n), sampling_weights(shifts)])
    if not groups or training < 2 * null.shape[1]:
        return None
    columns = {NULL_MODEL: list(range(null.shape[1]))}
    blocks = [null]
    for name in bases:
        extra = source_weights(get_basis(name), shifts, sensor_shape)[:, 1:]   # corrections
        start = sum(b.shape[1] for b in blocks)
        if training >= 2 * (null.shape[1] + extra.shape[1]):
            columns[f"{NULL_MODEL}+{name}"] = columns[NULL_MODEL] + list(
                range(start, start + extra.shape[1]))
            blocks.append(extra)
    design = np.column_stack(blocks)
    images = (stack.images / np.maximum(stack.gains, 1e-30)[:, None, None, None]).reshape(
        n, stack.images.shape[1], -1).astype(np.float64)
    mask = stack.valid.reshape(n, -1).astype(np.float64)
    gram, rhs = _sums(mask, images, design)
    held = np.concatenate(groups)
    norms = np.array([float(np.sum(images[p] ** 2, axis=0)[mask[p] > 0].sum()) for p in held])
    squared = {name: np.zeros(n) for name in columns}
    for group in groups:
        group_gram, group_rhs = _sums(mask[group], images[group], design[group])
        train_gram, train_rhs = gram - group_gram, rhs - group_rhs
        for name, cols in columns.items():
            kernels = solve_position_weights(train_gram[np.ix_(cols, cols)], train_rhs[cols])
            for p in group:
                prediction = np.einsum("kcn,k->cn", kernels, design[p, cols])
                residual = np.sum((prediction - images[p]) ** 2, axis=0)
                squared[name][p] = float(residual[mask[p] > 0].sum())
    return HeldOutErrors({name: values[held] for name, values in squared.items()}, norms)


def judge(stack: WorkingStack, center_row: int, sensor_shape: tuple[int, int],
          bases: list[str], folds: int = 9, effects: dict[str, Estimate] | None = None,
          progress: bool = False) -> tuple[CrossValidation, Verdict]:
    """Cross-validate the eigen-kernel ``bases`` (both conventions, plus ``"si"``) and the field
    models on a working stack, and decide (:func:`psfkit.fitting.verdict.decide`)."""
    from tqdm.auto import tqdm

    bases = list(dict.fromkeys(["si", *bases]))
    with tqdm(total=len(bases) + 1, desc="cross-validating models", unit="basis",
              disable=not progress) as bar:
        validation = cross_validate_positions(stack, bases, CONVENTIONS, center_row, folds,
                                              bar=bar)
        field_models = held_out_models(stack, center_row, sensor_shape, folds)
        bar.update()
    return validation, decide(candidate_models(validation), field_models, NULL_MODEL, effects)


def candidate_models(validation: CrossValidation) -> HeldOutErrors:
    """The forward models a user can write: ``"si"`` and ``"basis/convention"``."""
    held = validation.held_out.squared
    squared = {name: v for name, v in held.items()
               if name != CENTRE_ONLY and not name.startswith("si/")}
    if "si/sensor" in held:
        squared = {"si": held["si/sensor"], **squared}
    return HeldOutErrors(squared, validation.held_out.norms)


def moved_to(stack: WorkingStack, shifts_px: np.ndarray) -> WorkingStack:
    """The working copy with every PSF moved (Fourier shift) to be aligned at ``shifts_px``
    ``(P, 2)`` (full-resolution ``(du, dv)``), its valid blocks with it."""
    images = np.empty_like(stack.images)
    valid = np.empty_like(stack.valid)
    for p in range(len(stack.images)):
        move = (np.asarray(shifts_px[p], dtype=np.float64) / stack.factor - stack.shifts[p])
        step = (float(move[0]), float(move[1]))
        images[p], inside = shift_image(stack.images[p], step)
        valid[p] = inside & _moved_mask(stack.valid[p], step)
    # the same working copy (region, binning, positions) with the PSFs moved
    return dataclasses.replace(stack, images=images, valid=valid,
                               shifts=np.asarray(shifts_px, dtype=np.float64) / stack.factor)


def _moved_mask(mask: np.ndarray, step: tuple[float, float]) -> np.ndarray:
    """``mask`` moved by ``step`` ``(du, dv)``, keeping pixels whose floor/ceiling neighbours around
    ``x + s`` are all in ``mask``."""
    out = np.ones_like(mask)
    for dv in {math.floor(step[1]), math.ceil(step[1])}:
        for du in {math.floor(step[0]), math.ceil(step[0])}:
            out &= ndimage.shift(mask, (-dv, -du), order=0, cval=False)   # integer: exact
    return out
