"""The verdict: does the PSF shape change over the field, and which model to use.

:func:`decide` works on per-position *held-out* squared errors from cross-validation over
positions: ``null`` (one PSF plus sub-pixel sampling terms; its error is the **noise floor**),
``field`` (the null plus field-dependent weights) and ``candidates`` (``"si"`` and
``basis/convention``). It is ``shift_variant`` when the best field model beats the null
(mean per-position reduction of the relative squared error ``> Z·σ`` and one-sided Wilcoxon
``p < α(Z)``, :mod:`psfkit.numerics.significance`); the ``recommended_model`` is then the
candidate with the lowest held-out error if it beats ``"si"``, else ``"si"``. ``effects``
reports which field effects (shift, gain, warp, astigmatism) are significant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psfkit.numerics.significance import Z_SIGNIFICANT, Estimate, alpha, checked, undetermined

#: The shift-invariant model's name among the candidates.
SI = "si"
#: Field effects reported in ``effects`` (keys of :func:`decide`'s ``effects``).
EFFECTS = ("shift", "gain", "warp", "astigmatism")
EFFECT_WORDS = {"shift": "distortion beyond the linear shift map",
                "gain": "vignetting (gain falling off with field angle)",
                "warp": "growth of the warp residual with field angle",
                "astigmatism": "tangential/sagittal anisotropy (astigmatism)"}


@dataclass(frozen=True)
class HeldOutErrors:
    """Per-position held-out squared errors ``squared[name]`` ``(P,)`` of several models and the
    data's ``norms`` ``(P,)``, on the same positions."""

    squared: dict[str, np.ndarray]
    norms: np.ndarray

    @property
    def n_positions(self) -> int:
        return len(self.norms)

    def error(self, name: str) -> float:
        """Pooled relative error ``sqrt(Σ squared / Σ norms)`` (NaN without positions)."""
        total = float(np.sum(self.norms))
        return math.sqrt(float(np.sum(self.squared[name])) / total) if total > 0 else math.nan

    def sigma(self, name: str) -> float:
        """1σ of :meth:`error` over the positions (delta method)."""
        squared, norms = self.squared[name], self.norms
        n = len(norms)
        total = float(np.sum(norms))
        if n < 2 or total <= 0 or not np.sum(squared) > 0:
            return math.nan
        ratio = float(np.sum(squared)) / total
        var = n / (n - 1) * float(np.sum((squared - ratio * norms) ** 2)) / total**2
        return math.sqrt(var) / (2.0 * math.sqrt(ratio))

    def summary(self, name: str) -> dict[str, float]:
        return {"error": self.error(name), "sigma": self.sigma(name)}

    def improvement(self, worse: str, better: str) -> Estimate:
        """Mean per-position reduction of the relative squared error from ``worse`` to ``better``,
        with its standard error, tested one-sided (Wilcoxon signed-rank)."""
        diff = (self.squared[worse] - self.squared[better]) / self.norms
        n = len(diff)
        if n < 3:
            return undetermined(f"{n} held-out position(s); the comparison needs at least 3")
        sem = float(np.std(diff, ddof=1)) / math.sqrt(n)
        if not np.any(diff):
            return undetermined("the two models predict every held-out position alike")
        from scipy import stats  # here: 0.4 s of start-up for every command otherwise

        p_value = float(stats.wilcoxon(diff, alternative="greater").pvalue)
        return checked(float(np.mean(diff)), sem if sem > 0 else 1e-300, 0.0, p_value)


@dataclass(frozen=True)
class Verdict:
    """The verdict of :func:`decide`; ``to_dict`` is ``results.json["verdict"]``."""

    shift_variant: bool
    recommended_model: str
    evidence: dict[str, Any]
    effects: dict[str, dict[str, Any]]
    reason: str = ""
    field_test: Estimate = field(default_factory=lambda: undetermined("not run"))
    determined: bool = True

    @property
    def basis(self) -> str:
        """The recommended basis (``"si"`` for the shift-invariant model)."""
        return self.recommended_model.split("/")[0]

    @property
    def convention(self) -> str | None:
        """The recommended convention (``None`` for ``"si"``)."""
        parts = self.recommended_model.split("/")
        return parts[1] if len(parts) > 1 else None

    @property
    def significant_effects(self) -> list[str]:
        return [name for name in EFFECTS if self.effects.get(name, {}).get("significant")]

    def sentence(self) -> str:
        """The verdict in plain words (the report's first line)."""
        if not self.determined:
            head = (f"Too few positions to tell whether the PSF shape changes over the field "
                    f"({self.reason}): the shift-invariant model (one PSF) is the default.")
        elif not self.shift_variant:
            head = ("The PSF shape does not change over the field beyond noise: one PSF (a "
                    "shift-invariant model) is enough.")
        elif self.recommended_model == SI:
            head = ("The PSF shape changes over the field beyond noise, but no eigen-kernel "
                    "basis predicts held-out positions better than one PSF: use the "
                    "shift-invariant model.")
        else:
            head = (f"The PSF shape varies over the field beyond noise: use the eigen-kernel "
                    f"model {self.recommended_model}.")
        if self.reason and self.determined:
            head += f" ({self.reason})"
        effects = self.significant_effects
        measured = [name for name in EFFECTS
                    if self.effects.get(name, {}).get("status", "not determined")
                    != "not determined"]
        if effects:
            tail = "Significant field effects: " + "; ".join(EFFECT_WORDS[e] for e in effects)
            return f"{head} {tail}."
        if measured:
            return f"{head} No field effect is significant ({', '.join(measured)} tested)."
        return head

    def to_dict(self) -> dict[str, Any]:
        return {"shift_variant": self.shift_variant,
                "recommended_model": self.recommended_model,
                "basis": self.basis, "convention": self.convention,
                "determined": self.determined,
                "summary": self.sentence(), "evidence": self.evidence,
                "effects": self.effects, **({"reason": self.reason} if self.reason else {})}


def min_positions() -> int:
    """Held-out positions needed to reach significance: a one-sided Wilcoxon test of ``n`` cannot
    go below ``p = 2⁻ⁿ``."""
    return math.ceil(math.log2(1.0 / alpha()))


def decide(candidates: HeldOutErrors | None, field_models: HeldOutErrors | None,
           null_name: str, effects: dict[str, Estimate] | None = None) -> Verdict:
    """The verdict from held-out errors (module docstring).

    Parameters
    ----------
    candidates : HeldOutErrors or None
        The usable forward models, ``"si"`` and ``"basis/convention"``.
    field_models : HeldOutErrors or None
        The null model ``null_name`` and the field models on the same positions.
    null_name : str
    effects : dict of str to Estimate, optional
        The field effects of :data:`EFFECTS` (missing: "not measured").

    Returns
    -------
    Verdict
        Undetermined (``"si"``, with a ``reason``) with too few positions for the test.
    """
    effect_table = {name: _effect(name, (effects or {}).get(name)) for name in EFFECTS}
    evidence: dict[str, Any] = {"rule": _rule()}
    if candidates is not None and candidates.n_positions > 0:
        evidence["positions"] = candidates.n_positions
        evidence["held_out"] = {name: candidates.summary(name) for name in candidates.squared}
        if SI in candidates.squared:
            evidence["noise_floor"] = {"model": SI, **candidates.summary(SI)}
    if field_models is None or len(field_models.squared) < 2 \
            or field_models.n_positions < min_positions():
        n = field_models.n_positions if field_models is not None else \
            evidence.get("positions", 0)
        reason = (f"{n} held-out positions; the test needs at least {min_positions()}, and "
                  "enough to fit the field models")
        return Verdict(False, SI, evidence, effect_table, reason, determined=False)
    evidence["positions"] = field_models.n_positions
    evidence["noise_floor"] = {"model": null_name, **field_models.summary(null_name)}
    tested = {name: field_models.summary(name) for name in field_models.squared
              if name != null_name}
    evidence["field_models"] = tested
    best_field = min(tested, key=lambda name: tested[name]["error"])
    test = field_models.improvement(null_name, best_field)
    evidence["field_test"] = {"model": best_field, "against": null_name,
                              "mean_reduction_of_relative_squared_error": test.to_dict()}
    shift_variant = bool(test.significant and test.value > 0)
    recommended, reason = SI, ""
    if shift_variant:
        recommended, reason = _recommend(candidates)
    return Verdict(shift_variant, recommended, evidence, effect_table, reason, test)


def _recommend(candidates: HeldOutErrors | None) -> tuple[str, str]:
    """The eigen-kernel candidate with the lowest held-out error if it beats ``"si"``."""
    models = [] if candidates is None else [name for name in candidates.squared if name != SI]
    if candidates is None or not models:
        return SI, "no eigen-kernel basis was cross-validated"
    best = min(models, key=candidates.error)
    if SI in candidates.squared and candidates.error(best) >= candidates.error(SI):
        return SI, ""
    return best, ""


def _effect(name: str, estimate: Estimate | None) -> dict[str, Any]:
    measured = estimate is not None
    estimate = estimate if estimate is not None else undetermined("not measured")
    return {"significant": estimate.significant, "status": estimate.status,
            "measured": measured, "meaning": EFFECT_WORDS[name],
            "estimate": estimate.to_dict()}


def _rule() -> str:
    return (f"shift-variant when a field-dependent model predicts held-out positions better "
            f"than the best field-independent one (one PSF with sub-pixel sampling terms): "
            f"mean per-position reduction of the relative squared error > "
            f"{Z_SIGNIFICANT:g}σ and one-sided Wilcoxon p < {alpha():.2g}")
