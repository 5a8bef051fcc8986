"""The verdict and the significance of the field effects against the virtual bench's truth
(issue 43): the default camera varies over the field, the field-free camera does not."""

from __future__ import annotations

import numpy as np
import pytest

from psfkit.characterization.characterize import characterize_grid
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.io import read_grid
from psfkit.numerics.significance import Z_SIGNIFICANT
from psfkit.simulate import read_ground_truth


@pytest.fixture(scope="module")
def default_camera(grid_5x5):
    return characterize_grid(read_grid(grid_5x5)), read_ground_truth(grid_5x5)


@pytest.fixture(scope="module")
def field_free_camera(grid_5x5_field_free):
    return (characterize_grid(read_grid(grid_5x5_field_free)),
            read_ground_truth(grid_5x5_field_free))


def test_default_camera_is_shift_variant_with_an_eigen_kernel_model(default_camera):
    result, truth = default_camera
    verdict = result.verdict
    assert verdict.shift_variant and verdict.determined
    assert verdict.basis != "si" and verdict.convention in ("sensor", "source")
    evidence = verdict.evidence
    assert evidence["positions"] == 24
    held = evidence["held_out"]
    assert held[verdict.recommended_model]["error"] < held["si"]["error"]
    assert verdict.field_test.significant and verdict.field_test.value > 0
    # vignetting: the cos⁴ of the bench, inside the rule's ±Zσ interval
    gain = result.gain_fit.estimate
    assert verdict.effects["gain"]["significant"] and gain.significant
    assert abs(gain.value - truth.config.vignetting_exponent) < Z_SIGNIFICANT * gain.sigma
    assert "vignetting" in verdict.sentence()


def test_field_free_camera_needs_one_psf_and_shows_no_effect(field_free_camera):
    result, truth = field_free_camera
    verdict = result.verdict
    assert verdict.determined and not verdict.shift_variant
    assert verdict.recommended_model == "si"
    assert verdict.significant_effects == []
    for name, effect in verdict.effects.items():
        assert effect["measured"], name
        assert not effect["significant"], name
    # no vignetting (exponent 0 inside the rule's ±Zσ), a linear shift map (no distortion)
    gain = result.gain_fit.estimate
    assert abs(gain.value) < Z_SIGNIFICANT * gain.sigma
    assert not result.shift_fit.distortion.significant
    assert result.shift_fit.estimates["magnification"].significant
    magnification = result.shift_fit.estimates["magnification"]
    true_m = truth.info["magnification_px_per_monitor_px"]
    assert abs(magnification.value - true_m) < 3 * magnification.sigma + 1e-4 * true_m
    assert verdict.sentence().startswith("The PSF shape does not change over the field")


@pytest.mark.parametrize(("camera", "grid"), [("default_camera", "grid_5x5"),
                                             ("field_free_camera", "grid_5x5_field_free")])
def test_fit_eigen_auto_follows_the_report_verdict(camera, grid, request):
    """fit-eigen --basis auto writes the model the report recommends (same placement, same
    held-out comparison), in one fit."""
    grid_dir = request.getfixturevalue(grid)
    report = request.getfixturevalue(camera)[0].verdict
    fit = fit_eigen_grid(read_grid(grid_dir), EigenFitOptions(basis="auto", convention="auto"))
    assert fit.verdict.recommended_model == report.recommended_model
    assert fit.verdict.shift_variant == report.shift_variant
    written = "si" if fit.basis_name == "si" else f"{fit.basis_name}/{fit.convention}"
    assert written == report.recommended_model
    model = fit.kernel_model()
    assert model.basis == fit.basis_name and model.convention == fit.convention
    assert np.isfinite(model.kernels).all()
    differences = fit.kernel_differences()
    if fit.basis_name == "si":
        assert differences == {}
    else:
        assert any(d.significant for d in differences.values())
