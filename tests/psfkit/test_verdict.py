"""The verdict's decision logic (psfkit.fitting.verdict) on made-up held-out errors: no images."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from psfkit.fitting.verdict import EFFECTS, HeldOutErrors, decide, min_positions
from psfkit.numerics.significance import Estimate, undetermined

NULL = "si+sampling"


def _errors(rng: np.random.Generator, n: int, **relative: float) -> HeldOutErrors:
    """Per-position squared errors: ``relative`` squared error per model, ±10 % scatter
    between positions (the same positions for every model: paired)."""
    norms = rng.uniform(0.5, 2.0, n)
    scatter = rng.normal(1.0, 0.1, n)
    return HeldOutErrors({name: level * norms * np.clip(scatter + rng.normal(0, 0.02, n),
                                                        0.1, None)
                          for name, level in relative.items()}, norms)


def _effects(significant: tuple[str, ...] = ()) -> dict[str, Estimate]:
    return {name: Estimate(4.0, 0.1, 0.0, 1e-9) if name in significant
            else Estimate(0.1, 0.2, 0.0, 0.6) for name in EFFECTS}


def test_a_field_model_that_predicts_better_makes_the_grid_shift_variant():
    rng = np.random.default_rng(0)
    field = _errors(rng, 24, **{NULL: 0.010, f"{NULL}+paper": 0.006, f"{NULL}+poly:2": 0.007})
    candidates = _errors(rng, 24, **{"si": 0.02, "paper/sensor": 0.012,
                                     "paper/source": 0.011, "poly:2/sensor": 0.013})
    verdict = decide(candidates, field, NULL, _effects(("gain", "astigmatism")))
    assert verdict.shift_variant and verdict.determined
    assert verdict.recommended_model == "paper/source"
    assert (verdict.basis, verdict.convention) == ("paper", "source")
    assert verdict.evidence["field_test"]["model"] == f"{NULL}+paper"
    assert verdict.evidence["noise_floor"]["model"] == NULL
    assert verdict.evidence["positions"] == 24
    assert verdict.significant_effects == ["gain", "astigmatism"]
    text = verdict.sentence()
    assert text.startswith("The PSF shape varies over the field beyond noise: use the "
                           "eigen-kernel model paper/source.")
    assert "vignetting" in text and "astigmatism" in text
    doc = verdict.to_dict()
    json.dumps(doc, allow_nan=False)
    assert doc["effects"]["gain"]["significant"] and not doc["effects"]["shift"]["significant"]
    for model in ("si", "paper/sensor", "paper/source"):
        assert doc["evidence"]["held_out"][model]["sigma"] > 0


def test_field_models_no_better_than_the_null_give_one_psf():
    rng = np.random.default_rng(1)
    field = _errors(rng, 24, **{NULL: 0.010, f"{NULL}+paper": 0.0102,
                                f"{NULL}+poly:2": 0.0110})
    candidates = _errors(rng, 24, **{"si": 0.011, "paper/sensor": 0.0115})
    verdict = decide(candidates, field, NULL, _effects())
    assert not verdict.shift_variant and verdict.recommended_model == "si"
    assert verdict.basis == "si" and verdict.convention is None
    assert verdict.sentence().startswith(
        "The PSF shape does not change over the field beyond noise: one PSF (a "
        "shift-invariant model) is enough.")
    assert "No field effect is significant" in verdict.sentence()


def test_an_improvement_at_a_few_positions_only_is_not_enough():
    """The same mean improvement, carried by 3 of 24 positions: the signed-rank test does not
    reject, so the rule's second half says no."""
    rng = np.random.default_rng(2)
    field = _errors(rng, 24, **{NULL: 0.010, f"{NULL}+paper": 0.010})
    field.squared[f"{NULL}+paper"][:3] *= 0.2
    field.squared[f"{NULL}+paper"][3:] *= 1.02
    verdict = decide(None, field, NULL)
    assert not verdict.field_test.significant and not verdict.shift_variant


def test_too_few_positions_are_not_a_verdict_of_shift_invariance():
    rng = np.random.default_rng(3)
    n = min_positions() - 1
    field = _errors(rng, n, **{NULL: 0.010, f"{NULL}+paper": 0.002})
    verdict = decide(_errors(rng, n, si=0.01, **{"paper/sensor": 0.002}), field, NULL)
    assert not verdict.determined and verdict.recommended_model == "si"
    assert verdict.sentence().startswith("Too few positions to tell")
    assert decide(None, None, NULL).recommended_model == "si"
    assert min_positions() == 9          # 2⁻⁹ < α(3) = 0.0027 < 2⁻⁸


def test_shift_variant_but_no_basis_beats_one_psf_recommends_si():
    rng = np.random.default_rng(4)
    field = _errors(rng, 24, **{NULL: 0.010, f"{NULL}+paper": 0.005})
    candidates = _errors(rng, 24, si=0.010, **{"paper/sensor": 0.012})
    verdict = decide(candidates, field, NULL)
    assert verdict.shift_variant and verdict.recommended_model == "si"
    assert "no eigen-kernel basis predicts held-out positions better than one PSF" \
        in verdict.sentence()


def test_effects_not_measured_are_said_so_and_never_print_nan():
    rng = np.random.default_rng(5)
    field = _errors(rng, 12, **{NULL: 0.010, f"{NULL}+paper": 0.0101})
    verdict = decide(None, field, NULL, {"gain": undetermined("no field angles")})
    doc = verdict.to_dict()
    assert doc["effects"]["shift"]["measured"] is False
    assert doc["effects"]["gain"]["status"] == "not determined"
    assert not re.search(r"\bnan\b", json.dumps(doc))
    assert "No field effect" not in verdict.sentence()      # nothing was tested


def test_held_out_error_and_its_sigma():
    squared = np.array([1.0, 4.0, 2.0, 3.0])
    norms = np.array([100.0, 100.0, 100.0, 100.0])
    errors = HeldOutErrors({"m": squared}, norms)
    assert errors.error("m") == pytest.approx(np.sqrt(10 / 400))
    # delta method: var(Σs/Σn) = n/(n−1) Σ(s − r n)² / (Σn)², σ_e = σ_r / (2e)
    r = 10 / 400
    var = 4 / 3 * np.sum((squared - r * norms) ** 2) / 400**2
    assert errors.sigma("m") == pytest.approx(np.sqrt(var) / (2 * np.sqrt(r)))


def test_no_held_out_position_gives_no_number_and_no_crash():
    empty = HeldOutErrors({"si": np.zeros(0)}, np.zeros(0))
    assert np.isnan(empty.error("si")) and np.isnan(empty.sigma("si"))
    verdict = decide(empty, None, NULL)
    assert not verdict.determined and "positions" not in verdict.evidence
    json.dumps(verdict.to_dict(), allow_nan=False)
