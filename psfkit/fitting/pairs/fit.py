r"""Forward models fitted to (scene, measurement) pairs (``psfkit fit-pairs``, ``eval-model``).

The kernels of a shift-invariant or eigen-kernel model ``y = A_K x`` (:mod:`psfkit.forward`,
the model ekdun trains with) are estimated by regularised least squares,

.. math::

    \min_K \sum_i \lVert A_K x_i - y_i\rVert^2 + \lambda\lVert K\rVert^2
           + \mu \sum_{k\ge1}\lVert K_k - K_0\rVert^2 ,

whose normal equations are solved **to convergence** by preconditioned CG streaming the pairs
(:mod:`psfkit.fitting.pairs.solver`). ``λ`` and ``μ`` default to 0 or are chosen by held-out
error (:mod:`psfkit.fitting.pairs.regularisation`), relative to the mean scene power; per-image
normalised data get one scale per pair (``fit_scale``). By default the kernels are then made
non-negative by projected Newton-CG from the unconstrained solution (:func:`_newton_start`),
optionally inside a support; a support alone is solved exactly by CG restricted to it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.errors import InvalidInputError
from psfkit.fitting.pairs.batches import DEFAULT_CACHE_BYTES, PairBatches
from psfkit.fitting.pairs.binning import downsample_pairs, upsampled_kernels
from psfkit.fitting.pairs.constraints import auto_support, newton_fit, support_least_squares
from psfkit.fitting.pairs.options import NEWTON_CG_ITERATIONS, PairFitOptions
from psfkit.fitting.pairs.regularisation import (
    FOLD_TOLERANCE,
    PATHS,
    RegularisationChoice,
    choose_regularisation,
    convention_record,
    held_out_metric,
    held_out_score,
    selection_binning,
)
from psfkit.fitting.pairs.result import PairFit
from psfkit.fitting.pairs.solver import solve_kernels
from psfkit.forward.geometry import CONVENTIONS
from psfkit.forward.kernel_space import KernelSpaceOperator
from psfkit.forward.kernelfile import KernelModel
from psfkit.forward.operator import SpectralOperator
from psfkit.forward.weights import get_basis
from psfkit.io.validation import MIN_PAIR_SIDE

__all__ = ["START_TOLERANCE", "KernelSpaceOperator", "PairFitOptions",
           "downsample_pairs", "fit_pairs", "leave_one_out", "predict", "relative_errors",
           "upsampled_kernels"]


def fit_pairs(scenes: np.ndarray, measurements: np.ndarray,
              options: PairFitOptions | None = None, initial: np.ndarray | None = None,
              dtype: torch.dtype = torch.float64, device: str = "cpu",
              progress: bool = False, support_mask: np.ndarray | None = None,
              batch_size: int | None = None, cache_bytes: int = DEFAULT_CACHE_BYTES
              ) -> PairFit:
    """Fit a forward model to ``(N, C, H, W)`` scenes and measurements (module docstring).

    Memory is that of the pairs plus ``cache_bytes`` of scene spectra, whatever their number.

    Parameters
    ----------
    scenes, measurements : numpy.ndarray
        ``(N, C, H', W')`` each.
    options : PairFitOptions
    initial : numpy.ndarray, optional
        ``(K, C, Hk, Wk)`` warm start (the solution does not depend on it).
    dtype : torch.dtype
        Working precision (float64: float32 cannot reach the tolerance on ill-conditioned data).
    support_mask : numpy.ndarray, optional
        ``(H', W')`` footprint (nonzero = inside) for ``options.support == "mask"``.
    batch_size, cache_bytes
        Pairs per batch (default :func:`~psfkit.fitting.pairs.batches.auto_batch_size`) and bytes
        of scene spectra kept between passes.

    Raises
    ------
    InvalidInputError
        Mismatched shapes, no pairs, or a support mask missing or of the wrong size.
    """
    options = options or PairFitOptions()
    if scenes.shape != measurements.shape or scenes.ndim != 4 or len(scenes) == 0:
        raise InvalidInputError(f"scenes {scenes.shape} and measurements {measurements.shape} "
                                "must both be (N, C, H, W) with N >= 1")
    if (options.support == "mask") != (support_mask is not None):
        raise InvalidInputError("a support mask is given exactly when options.support is "
                                f"'mask' (support {options.support!r})")
    if support_mask is not None and tuple(support_mask.shape) != tuple(scenes.shape[-2:]):
        raise InvalidInputError(f"the support mask is {support_mask.shape[0]}x"
                                f"{support_mask.shape[1]}, the kernels "
                                f"{scenes.shape[-2]}x{scenes.shape[-1]}")
    from tqdm.auto import tqdm

    with tqdm(unit="it", leave=False, desc=f"fit {options.basis}", disable=not progress) as bar:
        trial = _set_up(scenes, measurements, options, initial, batch_size, cache_bytes, dtype,
                        device, progress, bar)
        batches, options = trial.batches, trial.options
        # non-negative kernels (a constrained fit) start from float32 unconstrained ones
        unconstrained = _newton_start if options.solver == "newton" else _solve
        kernels, system = unconstrained(batches, measurements, options, trial.weights,
                                        trial.kernels, trial.history, bar)
        support = None
        if options.constrained:
            t0 = time.perf_counter()
            kernels, support, info_c = _constrained_solve(system, kernels, options,
                                                          support_mask, progress)
            info_c.update(passes=batches.passes, seconds=round(time.perf_counter() - t0, 3))
            trial.history.append(info_c)
    err, norm, _num, _den = batches.residual_norms(kernels, measurements)
    errors = err / norm.clamp_min(1e-300)
    # solved in ``dtype`` (float64 by default); handed over as psfkit's float32 arrays
    # (docs/architecture.md), so that a PairFit's kernels build the same operators as a
    # kernel file's
    return PairFit(kernels=kernels.to(torch.float32).cpu().numpy(), basis=options.basis,
                   convention=options.convention,
                   scales=batches.scales.to(torch.float32).cpu().numpy(),
                   training_error=errors.to(torch.float32).cpu().numpy(),
                   history=trial.history, options=options, support=support,
                   weights=trial.weights, regularisation=trial.choices,
                   convention_choice=trial.convention_choice)


@dataclasses.dataclass
class _Trial:
    """One convention's set-up of a fit (``held_out``: ``None`` when nothing was held out)."""

    batches: PairBatches
    options: PairFitOptions
    weights: dict[str, float]
    kernels: Tensor | None
    history: list[dict[str, Any]]
    choices: list[RegularisationChoice]
    held_out: list[float] | None = None
    convention_choice: dict[str, Any] | None = None


def _set_up(scenes: np.ndarray, measurements: np.ndarray, options: PairFitOptions,
            initial: np.ndarray | None, batch_size: int | None, cache_bytes: int,
            dtype: torch.dtype, device: str, progress: bool, bar: Any) -> _Trial:
    """The pairs, weights and warm start of the fit. With ``convention="auto"`` (eigen-kernels, at
    least two pairs) both conventions are set up with weights chosen on the same folds, and the
    one predicting held-out pairs better is kept; otherwise the given one (or sensor)."""
    n_kernels = get_basis(options.basis).n_kernels
    conventions = ((options.convention,) if options.convention != "auto" else
                   CONVENTIONS if n_kernels > 1 and len(scenes) >= 2 else ("sensor",))
    seed = None                     # (kernels, scales): one SI fit serves every convention
    if initial is None and n_kernels > 1 and options.seed_with_si:
        # every kernel at the shift-invariant fit, with that fit's per-pair scales
        si = fit_pairs(scenes, measurements,
                       dataclasses.replace(options, basis="si", convention="sensor",
                                           nonneg=False, support="none",
                                           tikhonov=options.weights()["tikhonov"]),
                       dtype=dtype, device=device, progress=progress,
                       batch_size=batch_size, cache_bytes=cache_bytes)
        seed = (torch.as_tensor(np.repeat(si.kernels, n_kernels, axis=0), dtype=dtype,
                                device=device),
                torch.as_tensor(si.scales, dtype=dtype, device=device))
    trials = []
    for convention in conventions:
        opts = dataclasses.replace(options, convention=convention)
        batches = PairBatches(scenes, opts.basis, convention, tuple(scenes.shape[-2:]),
                              opts.scene_padding, batch_size, cache_bytes, dtype, device)
        trial = _Trial(batches, opts, opts.weights(), None, [], [])
        if initial is not None:
            trial.kernels = torch.as_tensor(initial, dtype=dtype, device=device).clone()
        elif seed is not None:
            trial.kernels, batches.scales = seed[0].clone(), seed[1].clone()
        if (opts.automatic or len(conventions) > 1) and batches.n >= 2:
            trial.kernels, trial.held_out = _choose_weights(
                batches, measurements, opts, trial.weights, trial.kernels, trial.history,
                trial.choices, bar)
        trials.append(trial)
    if len(trials) == 1:
        return trials[0]
    # two conventions only with at least two pairs, so both were scored
    record = convention_record({t.options.convention: t.held_out for t in trials
                                if t.held_out is not None},
                               held_out_metric(options.fit_scale))
    chosen = next(t for t in trials if t.options.convention == record["chosen"])
    chosen.convention_choice = record
    return chosen


def _choose_weights(batches: PairBatches, measurements: np.ndarray, options: PairFitOptions,
                    weights: dict[str, float], kernels: Tensor | None,
                    history: list[dict[str, Any]], choices: list[RegularisationChoice],
                    bar: Any) -> tuple[Tensor | None, list[float]]:
    """Choose ``options.automatic``'s weights by held-out error (into ``weights``; records into
    ``choices``), in float32 on pairs binned to at most ``SELECTION_PIXELS``: the scales first at
    the strongest weights, then the folds. Returns the warm start at the chosen weights
    (upsampled when binned) and the held-out errors at the model's weights (a chosen
    conditioning ridge left out)."""
    factor = selection_binning(batches.sensor, MIN_PAIR_SIDE)
    # the scales at the strongest weight of the first choice (an eigen-kernel ridge, chosen
    # second, at none)
    strongest = {**weights, **{p: PATHS[p][0] for p in options.automatic[:1]}}
    if factor > 1:
        scenes, measured = downsample_pairs(np.asarray(batches.scenes), np.asarray(measurements),
                                            factor)
        twin = PairBatches(scenes, options.basis, options.convention, scenes.shape[-2:],
                           options.scene_padding, None, batches.cache_bytes, torch.float32,
                           batches.device)
        first = None
    else:
        twin, measured = batches.astype(torch.float32), measurements
        first = None if kernels is None else kernels.to(torch.float32)
    start, system = _solve(twin, measured, options, strongest, first, history, bar,
                           stage="scales", tolerance=FOLD_TOLERANCE)
    # a pair's scale is its gain, whatever the pixel pitch
    batches.scales = twin.scales.to(dtype=batches.dtype, device=batches.device)
    ridge = options.conditioning_ridge
    for parameter in options.automatic:
        bar.set_description(f"choose --{parameter} ({options.basis})")
        choice, start = choose_regularisation(
            twin, measured, parameter,
            {p: w for p, w in weights.items() if p != parameter}, options.fit_scale,
            system["reference"], start, bar,
            conditioning=parameter == ridge)
        choice.binning = factor
        weights[parameter] = choice.chosen
        choices.append(choice)
    # the conventions are compared at the model's weights, without a chosen conditioning ridge:
    # it must not pick the model (on DLMD at 1/4 resolution it tipped a fold to the sensor
    # side, and that fold's reconstruction lost 0.68 dB)
    decisive = [c for c in choices if c.parameter != ridge]
    if decisive:
        held_out = decisive[0].per_pair[decisive[0].weights.index(decisive[0].chosen)]
    else:
        unconditioned = {**weights, **({ridge: 0.0} if ridge in options.automatic else {})}
        held_out = held_out_score(twin, measured, unconditioned, options.fit_scale,
                                  system["reference"], start, bar)
    bar.set_description(f"fit {options.basis}")
    if factor > 1:
        # the binned fit's corrections on the unbinned grid, added to the given start's
        # detail: a closer start for the first full-resolution solve (DLMD: 276 CG iterations
        # instead of 400)
        fine = upsampled_kernels(start, factor, batches.kernel_shape).to(
            dtype=batches.dtype, device=batches.device)
        return (fine if kernels is None else kernels + (fine - fine[:1])), held_out
    return start.to(dtype=batches.dtype, device=batches.device), held_out


#: Relative residual of the float32 solves that start the non-negative solve (the
#: unconstrained kernels and the per-pair scales, which Newton keeps): 1e-5 is what float32
#: reaches, and it gives the scales of noise-free pairs as float64 solves do, where 1e-4 leaves
#: them 8e-4 off (tests/psfkit/test_pairs_solver.py); in less than half the time of float64.
START_TOLERANCE = 1e-5


def _newton_start(batches: PairBatches, measurements: np.ndarray, options: PairFitOptions,
                  weights: dict[str, float], kernels: Tensor | None,
                  history: list[dict[str, Any]], bar: Any) -> tuple[Tensor, dict[str, Any]]:
    """The non-negative solve's start: unconstrained kernels and per-pair scales solved in float32
    to ``START_TOLERANCE`` (stage ``"start"``), and the float64 system."""
    twin = batches.astype(torch.float32)
    start, _ = _solve(twin, measurements, options, weights,
                      None if kernels is None else kernels.to(torch.float32), history, bar,
                      stage="start", tolerance=START_TOLERANCE)
    batches.scales = twin.scales.to(batches.dtype)
    kernels, _info, system = solve_kernels(batches, measurements, weights["tikhonov"],
                                           weights["difference"],
                                           start=start.to(batches.dtype), max_iterations=0)
    system["twin"] = twin
    return kernels, system


def _solve(batches: PairBatches, measurements: np.ndarray, options: PairFitOptions,
           weights: dict[str, float], kernels: Tensor | None, history: list[dict[str, Any]],
           bar: Any, stage: str = "fit", tolerance: float | None = None
           ) -> tuple[Tensor, dict[str, Any]]:
    """The unconstrained kernels at the relative ``weights``, the per-pair scales re-estimated over
    ``options.rounds`` warm-started solves (records appended to ``history``); returns the kernels
    and the last solve's system."""
    # Every round is solved to the tolerance (warm-started from the previous one): scales
    # fitted to loosely solved kernels are biased by a percent, and then stay so.
    scale_rounds = options.rounds - 1 if options.fit_scale else 0
    round_index = 0
    while True:
        final_round = round_index >= scale_rounds
        t0 = time.perf_counter()
        kernels, info, system = solve_kernels(
            batches, measurements, weights["tikhonov"], weights["difference"], start=kernels,
            tolerance=options.tolerance if tolerance is None else tolerance,
            max_iterations=options.final_iterations if final_round
            else options.scale_iterations, bar=bar)
        record = info.as_dict()
        record.update(stage=stage, round=round_index, passes=batches.passes,
                      seconds=round(time.perf_counter() - t0, 3),
                      **{k: system[k] for k in ("lambda", "mu", "reference")})
        history.append(record)
        if final_round:
            return kernels, system
        # the model is linear in the scene: fit the best scale to each unscaled prediction
        _err, _norm, num, den = batches.residual_norms(kernels, measurements)
        new = num / den.clamp_min(1e-30)
        new = new / new.mean()                       # the overall scale stays in the kernels
        if float((new - batches.scales).abs().max()) < 1e-6:
            scale_rounds = round_index + 1           # converged: go to the final solve
        batches.scales = new
        round_index += 1


def _constrained_solve(system: dict[str, Any], unconstrained: Tensor,
                       options: PairFitOptions, support_mask: np.ndarray | None,
                       progress: bool) -> tuple[Tensor, np.ndarray | None, dict[str, Any]]:
    """The final solve under ``options``' constraints, from the unconstrained kernels (whose base
    kernel gives the automatic support)."""
    support = None
    if options.support == "auto":
        support = auto_support(unconstrained[0].cpu().numpy(), options.support_threshold)
    elif options.support == "mask":
        support = np.asarray(support_mask) != 0
    mask = None if support is None else torch.as_tensor(support, device=unconstrained.device)
    if options.nonneg:
        kernels, info = newton_fit(system, unconstrained, mask,
                                   options.final_projected_iterations, NEWTON_CG_ITERATIONS,
                                   options.tolerance, progress)
    else:
        assert mask is not None                   # constrained without nonneg: a support
        kernels, info = support_least_squares(system, unconstrained, mask, options.tolerance,
                                              options.final_iterations)
    info["support_fraction"] = 1.0 if support is None else float(support.mean())
    return kernels, support, info


def predict(model: KernelModel, scenes: np.ndarray, dtype: torch.dtype = torch.float32,
            *, model_name: str = "", scenes_name: str = "scenes") -> np.ndarray:
    """Measurements ``(N, C, H', W')`` a kernel-file model predicts for ``scenes`` (``A x`` of
    :meth:`~psfkit.forward.operator.SpectralOperator.from_kernel_model`); ``model_name`` and
    ``scenes_name`` name the inputs when their sizes or channels disagree."""
    model_text = f"the model {model_name}" if model_name else "the model"
    if tuple(scenes.shape[-2:]) != tuple(model.sensor_shape):
        raise InvalidInputError(f"{scenes_name}: scenes are {scenes.shape[-2]}x"
                                f"{scenes.shape[-1]} but {model_text} has a "
                                f"{model.sensor_shape[0]}x{model.sensor_shape[1]} sensor")
    if scenes.shape[1] != len(model.channels):
        raise InvalidInputError(f"{scenes_name}: scenes have {scenes.shape[1]} channel(s) but "
                                f"{model_text} has {len(model.channels)} "
                                f"({'/'.join(model.channels)})")
    with torch.no_grad():
        op = SpectralOperator.from_kernel_model(model, dtype)
        return op.A(torch.as_tensor(scenes, dtype=dtype)).numpy()


def relative_errors(prediction: np.ndarray, measurements: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pair ``‖y − A x‖/‖y‖`` as predicted (``raw``) and with the best scale per pair
    (``scaled``)."""
    p = prediction.reshape(len(prediction), -1).astype(np.float64)
    y = measurements.reshape(len(measurements), -1).astype(np.float64)
    norm = np.linalg.norm(y, axis=1)
    raw = np.linalg.norm(p - y, axis=1) / norm
    scale = np.sum(p * y, axis=1) / np.maximum(np.sum(p * p, axis=1), 1e-30)
    scaled = np.linalg.norm(scale[:, None] * p - y, axis=1) / norm
    return {"raw": raw, "scaled": scaled, "scale": scale}


def leave_one_out(scenes: np.ndarray, measurements: np.ndarray, options: PairFitOptions,
                  progress: bool = False, support_mask: np.ndarray | None = None
                  ) -> dict[str, Any]:
    """Held-out errors: each pair predicted by the model fitted on all the others."""
    n = len(scenes)
    if n < 2:
        raise InvalidInputError("leave-one-out needs at least two pairs")
    from tqdm.auto import tqdm

    raw, scaled = np.zeros(n), np.zeros(n)
    for i in tqdm(range(n), desc=f"leave-one-out ({options.basis})", unit="fit",
                  disable=not progress):
        keep = np.arange(n) != i
        fit = fit_pairs(scenes[keep], measurements[keep], options,
                        support_mask=support_mask)
        errors = relative_errors(predict(fit.kernel_model(), scenes[i:i + 1]),
                                 measurements[i:i + 1])
        raw[i], scaled[i] = errors["raw"][0], errors["scaled"][0]
    return {"raw": raw, "scaled": scaled,
            "mean_raw": float(np.mean(raw)), "mean_scaled": float(np.mean(scaled)),
            "rms_raw": float(math.sqrt(np.mean(raw**2))),
            "rms_scaled": float(math.sqrt(np.mean(scaled**2)))}
