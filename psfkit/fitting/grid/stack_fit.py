"""Eigen-kernel models fitted and scored on a working stack: the fit, its in-sample errors, the
leave-positions-out cross-validation and the jackknifed kernel differences.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from psfkit.fitting.grid.design import predict_aligned
from psfkit.fitting.grid.eigen import DEFAULT_RIDGE, NormalEquations
from psfkit.fitting.grid.working_stack import WorkingStack
from psfkit.fitting.verdict import HeldOutErrors
from psfkit.forward.weights import WeightBasis, get_basis
from psfkit.numerics.significance import Estimate, checked, undetermined


def _squared(image: np.ndarray, valid: np.ndarray) -> float:
    """``Σ image²`` over the channels and the ``valid`` pixels of a ``(C, h, w)`` image."""
    return float(np.sum(image**2, axis=0)[valid].sum())


def fit_stack(stack: WorkingStack, basis: WeightBasis, convention: str,
              ridge: float = DEFAULT_RIDGE) -> tuple[np.ndarray, np.ndarray]:
    """Kernels ``(K, C, h, w)`` fitted on a working stack, and the per-pixel conditioning of the
    design ``(h, w)``."""
    kernels, conditioning = _equations(stack, basis, convention,
                                       range(len(stack.images))).solve(ridge)
    assert conditioning is not None
    return kernels, conditioning


def stack_residuals(stack: WorkingStack, kernels: np.ndarray, basis: WeightBasis,
                    convention: str) -> np.ndarray:
    """In-sample relative error ``‖pred − data‖ / ‖data‖`` ``(P,)`` of a model on every position
    of a working stack (valid pixels, all channels)."""
    out = []
    for p in range(len(stack.images)):
        norm = _squared(stack.images[p], stack.valid[p])
        error = _squared_error(stack, p, predict_aligned(kernels, basis, tuple(stack.shifts[p]),
                                                         convention, frame=stack.frame))
        out.append(math.sqrt(error / norm) if norm > 0 else float("nan"))
    return np.array(out)


def fold_groups(n: int, center_row: int, folds: int = 9, seed: int = 0) -> list[np.ndarray]:
    """The positions other than the centre in ``folds`` seeded random groups (the same groups for
    every cross-validation of a stack)."""
    others = np.array([p for p in range(n) if p != center_row])
    if len(others) == 0:
        return []
    rng = np.random.default_rng(seed)
    return np.array_split(rng.permutation(others), min(folds, len(others)))


@dataclass
class CrossValidation:
    """Per-position held-out errors of cross-validated models (:func:`cross_validate_positions`).

    ``held_out``: one entry per model (``"basis/convention"``, ``"centre PSF only"``);
    ``kernel_differences[model]``: ``(full, folds)``, the ``‖K_k − K_0‖² / ‖K_0‖²`` (k ≥ 1) of
    the kernels fitted on all positions ``(K − 1,)`` and per fold ``(G, K − 1)``.
    """

    held_out: HeldOutErrors
    folds: int
    kernel_differences: dict[str, tuple[np.ndarray, np.ndarray]]

    def to_dict(self) -> dict[str, Any]:
        """The ``cross_validation`` record: pooled errors, their 1σ, the best model."""
        names = list(self.held_out.squared)
        errors = {name: self.held_out.error(name) for name in names}
        best = min((k for k in errors if k != CENTRE_ONLY), key=errors.__getitem__,
                   default=None)
        return {"held_out_relative_error": errors,
                "held_out_sigma": {name: self.held_out.sigma(name) for name in names},
                "best": best, "folds": self.folds}


def squared_relative_differences(kernels: np.ndarray) -> np.ndarray:
    """``‖K_k − K_0‖² / ‖K_0‖²`` for k ≥ 1 of ``(K, C, h, w)`` kernels, ``(K − 1,)``."""
    base = float(np.sum(kernels[0].astype(np.float64) ** 2))
    return np.array([float(np.sum((kernels[k] - kernels[0]).astype(np.float64) ** 2))
                     / max(base, 1e-300) for k in range(1, len(kernels))])


def kernel_difference_estimates(full: np.ndarray, folds: np.ndarray, p_value: float
                                ) -> list[Estimate]:
    """Each eigen-kernel's ``‖K_k − K_0‖/‖K_0‖`` as an :class:`Estimate` from the delete-a-fold
    jackknife of its square (removing its noise bias; the spread over folds gives the 1σ).

    ``full`` and ``folds`` as in :attr:`CrossValidation.kernel_differences`; ``p_value`` that of
    the held-out field test.
    """
    g = len(folds)
    if g < 2:
        return [undetermined("fewer than two cross-validation folds") for _ in full]
    mean = folds.mean(axis=0)
    debiased = g * full - (g - 1) * mean
    spread = np.sqrt((g - 1) / g * np.sum((folds - mean) ** 2, axis=0))
    out = []
    for value2, se2 in zip(debiased, spread, strict=True):
        value = math.sqrt(max(float(value2), 0.0))
        # delta method on the square root, kept finite where the square is within its noise
        sigma = float(se2) / (2.0 * max(value, math.sqrt(float(se2)), 1e-300))
        out.append(checked(value, sigma, 0.0, p_value))
    return out


CENTRE_ONLY = "centre PSF only"


def cross_validate_positions(stack: WorkingStack, bases: list[str],
                             conventions: tuple[str, ...], center_row: int, folds: int = 9,
                             seed: int = 0, bar: Any = None) -> CrossValidation:
    """Leave-positions-out cross-validation of eigen-kernel models, per position.

    Each model is fitted without one group of :func:`fold_groups` (the centre, which defines the
    frame, is always kept) and predicts it; a fold's normal equations are the total minus its
    group's. The centre PSF alone is scored too. ``bar`` (tqdm) advances by one per basis.
    """
    n = len(stack.images)
    groups = fold_groups(n, center_row, folds, seed)
    held = np.concatenate(groups) if groups else np.zeros(0, int)
    training_size = n - max((len(g) for g in groups), default=0)
    norms = np.array([_squared(stack.images[p], stack.valid[p]) for p in held])
    centre = stack.images[center_row]
    squared = {CENTRE_ONLY: np.array([_squared_error(stack, p, centre) for p in held])}
    differences: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name in bases:
        basis = get_basis(name)
        usable = training_size >= basis.n_kernels     # else too few training positions
        for convention in conventions if usable else ():
            per_group = [_equations(stack, basis, convention, group) for group in groups]
            total = _equations(stack, basis, convention, [center_row])
            for eq in per_group:
                total += eq
            errors = {}
            fold_differences = []
            for group, eq in zip(groups, per_group, strict=True):
                kernels = total.minus(eq).solve(conditioning=False)[0]
                fold_differences.append(squared_relative_differences(kernels))
                for p in group:
                    errors[p] = _squared_error(stack, p, predict_aligned(
                        kernels, basis, tuple(stack.shifts[p]), convention, frame=stack.frame))
            key = f"{name}/{convention}"
            squared[key] = np.array([errors[p] for p in held])
            if basis.n_kernels > 1:
                full = squared_relative_differences(total.solve(conditioning=False)[0])
                differences[key] = (full, np.array(fold_differences))
        if bar is not None:
            bar.update()
    return CrossValidation(HeldOutErrors(squared, norms), len(groups), differences)


def _equations(stack: WorkingStack, basis: WeightBasis, convention: str,
               rows: Iterable[int]) -> NormalEquations:
    """The normal equations of the stack's ``rows``, added in order."""
    equations = NormalEquations(basis, convention, stack.images.shape[1:], frame=stack.frame)
    for p in rows:
        equations.add(stack.images[p], stack.valid[p], tuple(stack.shifts[p]))
    return equations


def _squared_error(stack: WorkingStack, p: int, prediction: np.ndarray) -> float:
    return _squared(prediction - stack.images[p], stack.valid[p])
