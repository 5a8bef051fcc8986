"""The regularisation of a pairs fit, chosen by held-out error (``fit-pairs``' default).

A few pairs do not determine every kernel pixel, while hundreds do and any prior only biases
them; so the weights (the ridge ``λ`` of ``si``; the difference prior ``μ`` of eigen-kernels,
then their ridge; relative to the mean scene power) are chosen by **cross-validation over
pairs**, one after the other:

* ``k = min(N, MAX_FOLDS)`` folds of consecutive pairs, scored until ``MIN_HELD_OUT`` pairs and
  ``MIN_FOLDS`` folds are held out;
* along :data:`PATHS` (strong to none, half a decade apart, then 0) each fold's unconstrained
  kernels are solved by preconditioned CG in float32 (warm-started along the path) and its
  held-out pairs predicted;
* a weight's score is the mean held-out ``‖a p − y‖ / ‖y‖`` (best gain ``a`` per pair when the
  fit estimates scales, else ``a = 1``);
* the path stops at the first weight worse than the best by more than ``TIE``; the chosen
  weight is the smallest within ``TIE`` of the lowest; if the strongest scores best, up to
  ``STRONGER_STEPS`` stronger ones are tried;
* the eigen-kernel ridge conditions the solve rather than regularising it: its path is
  :data:`CONDITIONING_PATH` and the *strongest* weight within ``TIE`` of the lowest wins (so
  pairs that determine the kernels keep the unbiased fit, and the others a faster one);
* pairs above :data:`SELECTION_PIXELS` pixels are binned for the choice.

The per-frequency Gram blocks would give exact leave-one-out only without the crop, so the
held-out errors come from fold solves (fixed per-pair scales, no constraint).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psfkit.fitting.pairs.batches import MeasurementSource, PairBatches
from psfkit.fitting.pairs.gram import FrequencyGram
from psfkit.fitting.pairs.solver import regularised_normal, solve_normal_equations

#: Relative weights tried, strongest first (then 0, the unbiased fit): ``λ`` for one PSF,
#: ``μ`` (difference prior) for eigen-kernels. Half a decade apart: on the DLMD pairs the
#: held-out error changes by about 1 % between neighbours near its minimum.
PATHS: dict[str, tuple[float, ...]] = {
    "tikhonov": tuple(round(10 ** (-j / 2), 6) for j in range(0, 9)),        # 1 … 1e-4
    "difference": tuple(round(10 ** (1 - j / 2), 6) for j in range(0, 9)),   # 10 … 1e-3
}
#: The eigen-kernel ridge's path: for conditioning only, so capped where it costs the DLMD
#: reconstruction nothing measurable (0.01: 0.05 ± 0.04 dB; the lowest held-out error there
#: lies at 0.316, which costs 0.18 dB: research/notes/forward-model-studies.md). Without a
#: ridge the directions the pairs barely see leave the non-negative solve 3x longer.
CONDITIONING_PATH = (0.01, 0.003162, 0.001, 0.000316, 0.0001)
#: When the path's strongest weight scores best, up to this many stronger weights (half a
#: decade apart) are tried until one scores worse (DLMD at full resolution chooses 10).
STRONGER_STEPS = 4
#: Most folds (leave-one-out up to this many pairs).
MAX_FOLDS = 8
#: Folds are scored until at least this many pairs, and ``MIN_FOLDS`` folds, were held out
#: (384 pairs: one fold of 48; the scores of the weights are compared on the same pairs).
MIN_HELD_OUT = 32
MIN_FOLDS = 1
#: Relative residual of the fold solves (float32): the held-out errors then agree with those
#: of fits solved to 1e-6 in float64 to ~1e-5 (measured on DLMD at 1/4 resolution).
FOLD_TOLERANCE = 1e-4
#: The conditioning path's fold solves: the ridge moves the solution by less than
#: ``FOLD_TOLERANCE`` (DLMD: no CG iteration at all below 0.01), so they are solved closer.
CONDITIONING_TOLERANCE = 1e-6
#: Most CG iterations of one fold solve at one weight.
FOLD_ITERATIONS = 500
#: Scores within this relative distance of the lowest count as equal (the smaller weight wins;
#: on :data:`CONDITIONING_PATH` the larger).
TIE = 1e-3
#: The weight is chosen on the pairs binned (block means) to at most this many pixels and
#: used at full resolution (the weights are relative to the scenes' mean per-frequency power):
#: the folds at full resolution cost minutes. Binned 2x or 3x, the choice is the
#: full-resolution one or half a decade below it, where the path is flat within its standard
#: error; paired over the DLMD pairs at 1/2 resolution, though, the binned choice predicts
#: held-out pairs 2.5-3.5 % worse (research/notes/forward-model-studies.md, stop 64).
SELECTION_PIXELS = 128 * 128


@dataclass
class RegularisationChoice:
    """The weight chosen by :func:`choose_regularisation`, and the evidence: ``weights[j]`` scored
    ``held_out[j]`` (mean over held-out pairs ``per_pair[j]``, standard error ``spread[j]``)."""

    parameter: str
    chosen: float
    fixed: dict[str, float]
    folds: int
    scored_folds: int
    held_out_pairs: int
    metric: str
    weights: list[float] = field(default_factory=list)
    held_out: list[float] = field(default_factory=list)
    spread: list[float] = field(default_factory=list)
    per_pair: list[list[float]] = field(default_factory=list)
    iterations: list[int] = field(default_factory=list)
    seconds: float = 0.0
    passes: int = 0
    #: The pairs were binned by this factor for the choice (:data:`SELECTION_PIXELS`).
    binning: int = 1
    #: The binned sensor ``(H, W)`` the folds were solved on.
    sensor: tuple[int, int] = (0, 0)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready record (kernel file provenance and the fit report)."""
        return {"method": "cross-validation over pairs", "parameter": self.parameter,
                "chosen": self.chosen, "fixed": self.fixed, "folds": self.folds,
                "scored_folds": self.scored_folds, "held_out_pairs": self.held_out_pairs,
                "metric": self.metric,
                "path": [{"weight": w, "held_out": e, "spread": s, "cg_iterations": it,
                          "per_pair": p}
                         for w, e, s, it, p in zip(self.weights, self.held_out, self.spread,
                                                   self.iterations, self.per_pair,
                                                   strict=True)],
                "seconds": round(self.seconds, 2), "passes": self.passes,
                "binning": self.binning, "sensor": list(self.sensor)}

    def summary(self) -> str:
        """One line: the choice, its held-out error and the path."""
        best = self.weights.index(self.chosen)
        how = (f"leave-one-out over {self.held_out_pairs} pairs"
               if self.held_out_pairs == self.folds == self.scored_folds else
               f"{self.folds}-fold cross-validation ({self.scored_folds} fold(s) scored, "
               f"{self.held_out_pairs} pairs held out)")
        if self.binning > 1:
            how += f", binned {self.binning}x to {self.sensor[0]}x{self.sensor[1]}"
        path = ", ".join(f"{w:g}: {e:.4f}" for w, e in zip(self.weights, self.held_out,
                                                         strict=True))
        return (f"regularisation: --{self.parameter} {self.chosen:g} chosen by {how}: held-out "
                f"error {self.held_out[best]:.4f} ± {self.spread[best]:.4f} ({self.metric}; "
                f"path {path})")


def folds_of(n: int) -> list[np.ndarray]:
    """The held-out pairs of each fold scored: ``k = min(n, MAX_FOLDS)`` folds of consecutive pairs
    (fold ``f``: ``⌊f n/k⌋ … ⌊(f+1) n/k⌋ − 1``), enough for ``MIN_HELD_OUT`` pairs and
    ``MIN_FOLDS`` folds."""
    if n < 2:
        raise ValueError("cross-validation needs at least two pairs")
    k = min(n, MAX_FOLDS)
    folds, held = [], 0
    for f in range(k):
        folds.append(np.arange(f * n // k, (f + 1) * n // k))
        held += len(folds[-1])
        if held >= MIN_HELD_OUT and len(folds) >= MIN_FOLDS:
            break
    return folds


def selection_binning(sensor: tuple[int, int], min_side: int) -> int:
    """The smallest factor that bins a ``sensor`` ``(H, W)`` to at most
    :data:`SELECTION_PIXELS` pixels, keeping both sides at least ``min_side``."""
    h, w = sensor
    factor = 1
    while (h // factor) * (w // factor) > SELECTION_PIXELS and \
            min(h // (factor + 1), w // (factor + 1)) >= min_side:
        factor += 1
    return factor


def held_out_errors(batches: PairBatches, kernels: Tensor,
                    measurements: np.ndarray | Tensor | MeasurementSource,
                    best_gain: bool) -> dict[int, float]:
    """``{pair: relative error}`` of the active pairs of ``batches`` predicted by ``kernels``
    (unscaled), with the best gain per pair when ``best_gain``."""
    out: dict[int, float] = {}
    for start, stop, _op, _s, p in batches.predictions(kernels.to(batches.dtype)):
        p = p.to(torch.float64)
        y = batches.measurement(measurements, start, stop).to(torch.float64)
        if best_gain:
            gain = (p * y).sum(dim=(1, 2, 3)) / p.pow(2).sum(dim=(1, 2, 3)).clamp_min(1e-300)
            p = p * gain[:, None, None, None]
        err = (p - y).pow(2).sum(dim=(1, 2, 3)).sqrt() / \
            y.pow(2).sum(dim=(1, 2, 3)).sqrt().clamp_min(1e-300)
        out.update(enumerate(err.tolist(), start=start))
    return out


def _absolute(parameter: str, weight: float, fixed: dict[str, float], reference: float
              ) -> tuple[float, float]:
    """``(λ, μ)`` absolute, from the path's relative weight and the fixed other one."""
    weights = dict(fixed)
    weights[parameter] = weight
    return weights["tikhonov"] * reference, weights["difference"] * reference


def choose_regularisation(batches: PairBatches,
                          measurements: np.ndarray | Tensor | MeasurementSource,
                          parameter: str, fixed: dict[str, float], best_gain: bool,
                          reference: float, start: Tensor | None = None, bar: Any = None,
                          conditioning: bool = False) -> tuple[RegularisationChoice, Tensor]:
    """Choose ``parameter`` (``"tikhonov"`` or ``"difference"``) by held-out error.

    Parameters
    ----------
    batches : PairBatches
        The pairs (``scales`` fixed), in the fold solves' precision (float32).
    measurements : array or callable
        ``(N, C, H', W')``.
    parameter : str
        The weight chosen; ``fixed`` gives the other one (relative).
    best_gain : bool
        Score with the best gain per held-out pair.
    reference : float
        The unit of the relative weights (:meth:`FrequencyGram.reference_power`).
    start : Tensor, optional
        Warm start of every fold at the path's first weight.
    bar : tqdm, optional
        Advanced by one per CG iteration.
    conditioning : bool
        A ridge for conditioning (eigen-kernels): the path :data:`CONDITIONING_PATH`, the
        strongest weight within ``TIE`` of the lowest chosen.

    Returns
    -------
    (RegularisationChoice, Tensor)
        The choice, and a warm start at the chosen weight (the folds' mean kernels).
    """
    t0, passes = time.perf_counter(), batches.passes
    folds = folds_of(batches.n)
    fixed = {"tikhonov": 0.0, "difference": 0.0, **fixed}
    path = _FoldPath(batches, measurements, folds, start, best_gain, bar,
                     lambda w: _absolute(parameter, w, fixed, reference),
                     CONDITIONING_TOLERANCE if conditioning else FOLD_TOLERANCE)
    for weight in (*(CONDITIONING_PATH if conditioning else PATHS[parameter]), 0.0):
        if path.worse(path.evaluate(weight)):
            break
    # the strongest weight won: the best may lie beyond the path's start
    for _ in range(0 if conditioning else STRONGER_STEPS):
        top = max(path.scores)
        if path.chosen() != top or len(path.scores) < 2:
            break
        path.restart_from(top)
        if path.worse(path.evaluate(round(top * math.sqrt(10), 6))):
            break
    chosen = path.chosen(strongest=conditioning)
    warm = torch.stack(path.at_weight[chosen]).mean(dim=0)
    weights = sorted(path.scores, reverse=True)
    scores, per_pair, iterations = zip(*(path.scores[w] for w in weights), strict=True)
    return RegularisationChoice(
        parameter=parameter, chosen=chosen, sensor=batches.sensor,
        fixed={k: v for k, v in fixed.items() if k != parameter},
        folds=min(batches.n, MAX_FOLDS), scored_folds=len(folds),
        held_out_pairs=int(sum(len(f) for f in folds)), metric=held_out_metric(best_gain),
        weights=weights, held_out=list(scores), spread=[_standard_error(e) for e in per_pair],
        per_pair=list(per_pair), iterations=list(iterations),
        seconds=time.perf_counter() - t0, passes=batches.passes - passes), warm


def held_out_metric(best_gain: bool) -> str:
    """What the held-out errors measure (the records' ``metric``)."""
    return "relative error with the best gain per pair" if best_gain else "relative error"


def held_out_score(batches: PairBatches,
                   measurements: np.ndarray | Tensor | MeasurementSource,
                   weights: dict[str, float], best_gain: bool, reference: float,
                   start: Tensor | None = None, bar: Any = None) -> list[float]:
    """Held-out errors, one per pair, of the folds of :func:`folds_of` at fixed relative
    ``weights`` (a model whose weights were given, on :func:`choose_regularisation`'s folds)."""
    path = _FoldPath(batches, measurements, folds_of(batches.n), start, best_gain, bar,
                     lambda _w: (weights["tikhonov"] * reference,
                                 weights["difference"] * reference))
    path.evaluate(0.0)
    return path.scores[0.0][1]


def convention_record(per_pair: dict[str, list[float]], metric: str) -> dict[str, Any]:
    """Choose an eigen-kernel model's convention by held-out error (``per_pair``: each convention's
    errors on the same pairs). The source side (each scene point's PSF blended: what a grid of
    point sources measures, and the better fit on the virtual bench and on DLMD) is kept unless
    the sensor side (Eq. 7) predicts better by more than ``TIE`` and by more than one standard
    error of the paired difference: the one-standard-error rule, so that a difference the folds
    cannot resolve does not choose (on DLMD two folds of seven went to the sensor side on ties,
    and their reconstructions lost; research/notes/forward-model-studies.md). Returns the kernel
    file's record (choice, means, standard errors, paired difference)."""
    sensor, source = (np.asarray(per_pair[c]) for c in ("sensor", "source"))
    diff = source - sensor
    spread = _standard_error(diff) if len(diff) > 1 else 0.0
    chosen = "sensor" if diff.mean() > max(TIE * sensor.mean(), spread) else "source"
    return {"method": "cross-validation over pairs, each convention at its own chosen "
                      "regularisation", "metric": metric, "chosen": chosen,
            "held_out": {c: float(np.mean(v)) for c, v in per_pair.items()},
            "spread": {c: _standard_error(v) for c, v in per_pair.items()},
            "source_minus_sensor": float(diff.mean()), "difference_spread": _standard_error(diff),
            "per_pair": {c: list(map(float, v)) for c, v in per_pair.items()}}


def _standard_error(values: list[float] | np.ndarray) -> float:
    """The standard error of the mean of ``values`` (NaN for fewer than two)."""
    n = len(values)
    return float(np.std(values, ddof=1) / math.sqrt(n)) if n > 1 else float("nan")


def convention_summary(record: dict[str, Any]) -> str:
    """One line: the convention chosen and the evidence."""
    other = "sensor" if record["chosen"] == "source" else "source"
    m, e = record["held_out"], record["spread"]
    return (f"convention: {record['chosen']} chosen by held-out error {m[record['chosen']]:.4f}"
            f" ± {e[record['chosen']]:.4f} against {other} {m[other]:.4f} ± {e[other]:.4f}"
            f" (source − sensor paired: {record['source_minus_sensor']:+.4f} ± "
            f"{record['difference_spread']:.4f})")


class _FoldPath:
    """The folds' kernels along the path of weights, and each weight's held-out errors."""

    def __init__(self, batches: PairBatches,
                 measurements: np.ndarray | Tensor | MeasurementSource,
                 folds: list[np.ndarray], start: Tensor | None, best_gain: bool, bar: Any,
                 absolute: Any, tolerance: float = FOLD_TOLERANCE) -> None:
        self.batches, self.measurements, self.tolerance = batches, measurements, tolerance
        self.best_gain, self.bar, self.absolute = best_gain, bar, absolute
        self.train = [~np.isin(np.arange(batches.n), held) for held in folds]
        # a fold's right-hand side and Gram blocks do not depend on the weight: one pass each
        self.rhs: list[Tensor] = []
        self.grams: list[FrequencyGram] = []
        for mask in self.train:
            with batches.only(mask):
                self.rhs.append(batches.rhs(measurements))
                self.grams.append(batches.gram())
        self.kernels: list[Tensor | None] = [
            None if start is None else start.to(batches.dtype) for _ in folds]
        #: ``weight: (score, per-pair errors, CG iterations)``
        self.scores: dict[float, tuple[float, list[float], int]] = {}
        #: the folds' kernels at the weights that may still be chosen
        self.at_weight: dict[float, list[Tensor]] = {}

    def evaluate(self, weight: float) -> float:
        """Score ``weight``, the folds warm-started from their current kernels."""
        lam, mu = self.absolute(weight)
        b = self.batches
        errors: dict[int, float] = {}
        iterations = 0
        for f, mask in enumerate(self.train):
            with b.only(mask):
                self.kernels[f], info = solve_normal_equations(
                    regularised_normal(b, lam, mu), self.rhs[f],
                    self.grams[f].preconditioner(lam, mu), self.kernels[f], self.tolerance,
                    FOLD_ITERATIONS, self.bar)
            iterations += info.iterations
            with b.only(~mask):
                errors.update(held_out_errors(b, self.kernels[f], self.measurements,
                                              self.best_gain))
        per_pair = [errors[i] for i in sorted(errors)]
        self.scores[weight] = (float(np.mean(per_pair)), per_pair, iterations)
        # keep the folds' kernels only where the weight may still be chosen (memory)
        self.at_weight[weight] = [k.clone() for k in self.kernels if k is not None]
        for w, v in self.scores.items():
            if self.worse(v[0]):
                self.at_weight.pop(w, None)
        return self.scores[weight][0]

    def worse(self, score: float) -> bool:
        """Worse than the lowest score so far by more than ``TIE``."""
        return score > min(v[0] for v in self.scores.values()) * (1 + TIE)

    def chosen(self, strongest: bool = False) -> float:
        """The smallest (or ``strongest``) weight within ``TIE`` of the lowest score."""
        pick = max if strongest else min
        return pick(w for w, v in self.scores.items() if not self.worse(v[0]))

    def restart_from(self, weight: float) -> None:
        """Warm-start the next weight from the folds' kernels at ``weight``."""
        self.kernels = [k.clone() for k in self.at_weight[weight]]
