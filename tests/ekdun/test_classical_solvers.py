"""The one ADMM-TV for any kernel model (shift-invariant, sensor-side and source-side update
rules) and the extended-scene operator, checked against an independent algorithm (PDHG)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from ekdun.errors import ConfigurationError
from ekdun.nets.tv_admm_steps import finite_differences, finite_differences_adjoint
from ekdun.physics.operators import EigenKernelOperator
from ekdun.reconstruction.admm import (
    ShiftInvariantRule,
    SourceSideRule,
    solve_tv,
    update_rule,
)
from ekdun.reconstruction.classical import ClassicalOptions, ModelReconstructor
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from psfkit.forward.geometry import centre_offset
from psfkit.forward.kernelfile import KernelModel
from psfkit.forward.norm import operator_norm
from psfkit.forward.padded_scene import padded_scene_adjoint, padded_scene_forward

SENSOR = (20, 28)


def tv_objective(op: ExtendedSceneOperator, x: torch.Tensor, y: torch.Tensor,
                 weight: float) -> float:
    """``½‖A x − y‖² + weight·‖Ψx‖₁`` for ``x`` ``(1, C, PH, PW)`` and ``y`` ``(1, C, H', W')``
    (``weight = tv · peak(|y|) · ‖A‖`` is :func:`solve_tv`'s objective)."""
    r = op.A(x) - y
    return float(0.5 * (r * r).sum() + weight * finite_differences(x).abs().sum())


def _model(convention: str = "sensor", basis: str = "paper") -> KernelModel:
    rng = np.random.default_rng(1)
    n = 3 if basis == "paper" else 1
    kernels = rng.random((n, 1, 7, 9)) ** 4
    kernels -= 0.05 * rng.random(kernels.shape)          # negative lobes, as fit-pairs writes
    return KernelModel(kernels=kernels.astype(np.float32), basis=basis, convention=convention,
                       sensor_shape=SENSOR, channels=("L",))


def _problem(dtype=torch.float64, convention: str = "sensor", basis: str = "paper"):
    ext = ExtendedSceneOperator.from_kernel_model(_model(convention, basis), dtype=dtype)
    scene = torch.zeros((1, 1, *ext.grid_shape), dtype=dtype)
    scene[..., 12:30, 10:40] = 1.0
    scene[..., 20:26, 20:30] = 0.3
    y = ext.A(scene)
    noise = torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=dtype)
    return ext, scene, (y + 0.01 * y.abs().max() * noise)[0]


def pdhg_tv(measurement, op, tv, iterations, nonneg=True, tol=0.0, objective=False):
    """An independent reference for :func:`solve_tv`'s objective: Chambolle–Pock (2011,
    Algorithm 1, θ = 1) on ``K = [A/‖A‖; Ψ/√8]`` with only ``A`` and ``Aᵀ`` (the product's
    ``--solver pdhg`` until issue 44, removed there: ADMM won on every form). Same units as
    :func:`solve_tv`; returns ``(image, objectives per iteration, iterations, changes)``."""
    y = measurement[None]
    peak, norm = float(y.abs().max()), operator_norm(op)
    y_n, bound, root8 = y / peak, tv * math.sqrt(8.0), math.sqrt(8.0)
    step = 0.99 / math.sqrt(1.05 ** 2 + 1.0)       # σ t ‖K‖² < 1 for ‖A‖ up to 5 % above
    x = torch.zeros_like(op.A_adjoint(y_n))
    x_bar, p, q = x, torch.zeros_like(y_n), torch.zeros((2, *x.shape), dtype=y.dtype)
    objectives, changes = [], []
    for _ in range(iterations):
        p = (p + step * (op.A(x_bar) / norm - y_n)) / (1.0 + step)
        q = (q + (step / root8) * finite_differences(x_bar)).clamp(-bound, bound)
        x_new = x - step * (op.A_adjoint(p) / norm + finite_differences_adjoint(q) / root8)
        x_new = x_new.clamp_min(0) if nonneg else x_new
        changes.append(float((x_new - x).norm() / x_new.norm().clamp_min(1e-30)))
        x_bar, x = 2 * x_new - x, x_new
        if objective:
            objectives.append(tv_objective(op, x * (peak / norm), y, tv * peak * norm))
        if tol > 0 and changes[-1] < tol:
            break
    return (x * (peak / norm))[0], objectives, len(changes), changes


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_extended_operator_matches_the_sensor_sized_model_and_is_adjoint(convention):
    model = _model(convention)
    op = EigenKernelOperator.from_kernel_model(model, dtype=torch.float64).prepare()
    ext = ExtendedSceneOperator.from_kernel_model(model, dtype=torch.float64)
    assert ext.convention == convention
    g = torch.Generator().manual_seed(3)
    x = torch.randn((2, 1, *SENSOR), generator=g, dtype=torch.float64)
    torch.testing.assert_close(ext.A(ext.pad(x)), op.A(x), rtol=1e-12, atol=1e-12)
    big = torch.randn((2, 1, *ext.grid_shape), generator=g, dtype=torch.float64)
    y = torch.randn((2, 1, *SENSOR), generator=g, dtype=torch.float64)
    lhs, rhs = float((ext.A(big) * y).sum()), float((big * ext.A_adjoint(y)).sum())
    assert abs(lhs - rhs) < 1e-10 * abs(lhs)
    # the operator is psfkit's padded-grid Eq. 7 with the model's (edge-continued) weights
    weights = (torch.as_tensor(model.weight_maps(extent=ext.grid_shape)) if convention == "source"
               else torch.as_tensor(model.weight_maps()))
    spectra = op.spectra
    torch.testing.assert_close(
        ext.A(big), padded_scene_forward(big, spectra, weights, SENSOR, convention),
        rtol=0, atol=1e-12)
    torch.testing.assert_close(
        ext.A_adjoint(y), padded_scene_adjoint(y, spectra.conj(), weights, ext.grid_shape,
                                               convention), rtol=0, atol=1e-12)


def test_source_side_scene_weights_continue_the_edge_weights():
    model = _model("source")
    ext = ExtendedSceneOperator.from_kernel_model(model, dtype=torch.float64)
    weights = ext.scene_weights.numpy()
    top, left = centre_offset(SENSOR, ext.grid_shape)
    inside = weights[:, top:top + SENSOR[0], left:left + SENSOR[1]]
    np.testing.assert_allclose(inside, model.weight_maps(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(weights[:, 0, 0], inside[:, 0, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(weights[:, top + 3, -1], inside[:, 3, -1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(weights.sum(axis=0), 1.0, atol=1e-12)
    base = EigenKernelOperator.from_kernel_model(model, dtype=torch.float64).prepare()
    with pytest.raises(ConfigurationError, match="padded grid"):
        ExtendedSceneOperator(base)
    with pytest.raises(ConfigurationError, match="equal the model's weights"):
        ExtendedSceneOperator(base, torch.roll(ext.scene_weights, 1, dims=-1))
    # The model's form picks the update rule; penalties of another rule are refused.
    assert update_rule(ext) is SourceSideRule
    si = ExtendedSceneOperator.from_kernel_model(_model("source", "si"), dtype=torch.float64)
    assert update_rule(si) is ShiftInvariantRule              # one kernel: either convention
    with pytest.raises(ConfigurationError, match="mu4"):
        solve_tv(torch.zeros((1, *SENSOR), dtype=torch.float64), si, mu={"mu4": 0.1})


FORMS = [("sensor", "paper"), ("source", "paper"), ("sensor", "si")]


@pytest.mark.parametrize(("convention", "basis"), FORMS[:2])
def test_admm_and_pdhg_reach_the_same_minimiser_for_every_form(convention, basis):
    # Two different algorithms on one objective (the same ‖A‖ estimate, so the same --tv is the
    # same weight), run far past where they stop moving: one minimiser, for the sensor- and
    # source-side rules. The shift-invariant rule is the sensor-side one with unit weights
    # (iterate for iterate, below); on its toy problem PDHG is still 3e-5 above ADMM's
    # objective after 4000 iterations (measured), too slow a reference for a fast test.
    ext, scene, y = _problem(convention=convention, basis=basis)
    tv = 3e-3
    pdhg, objective, _, _ = pdhg_tv(y, ext, tv=tv, iterations=4000, objective=True)
    norm = operator_norm(ext)
    weight = tv * float(y.abs().max()) * norm
    objective = np.array(objective)
    assert objective[-1] < 0.05 * objective[0]
    # PDHG is not monotone step by step, but decreases over the run.
    checkpoints = objective[[0, 50, 300, 1000, 3999]]
    assert np.all(np.diff(checkpoints) < 0), checkpoints
    # The penalties change the speed, not the minimiser: the DLMD-tuned source-side defaults
    # need ~20000 iterations on this toy problem, these 5000.
    penalties = {"source": {"mu1": 0.5, "mu2": 0.05, "mu3": 0.05, "mu4": 0.5}}
    admm = solve_tv(y, ext, tv=tv, iterations=5000, nonneg=True,
                    mu=penalties.get(ext.convention))
    assert admm.operator_norm == norm
    a, p = admm.image[None], pdhg[None]
    assert float(a.min()) >= 0
    obj_admm, obj_pdhg = tv_objective(ext, a, y[None], weight), tv_objective(ext, p, y[None],
                                                                             weight)
    assert abs(obj_admm - obj_pdhg) < 1e-5 * obj_pdhg
    # One minimiser (the scene in view is what they must agree on).
    assert float((ext.crop(a) - ext.crop(p)).norm() / ext.crop(p).norm()) < 1e-4
    # The minimiser beats the true scene on the objective, and both reconstruct it.
    assert obj_pdhg <= tv_objective(ext, scene, y[None], weight)
    inside = ext.crop(scene)
    assert float((ext.crop(p) - inside).norm() / inside.norm()) < 0.25


def test_shift_invariant_rule_is_the_sensor_side_rule_with_unit_weights():
    from ekdun.reconstruction.admm import SensorSideRule, normalised_problem

    ext, _, y = _problem(convention="sensor", basis="si")
    mu = SensorSideRule.penalties
    problem = normalised_problem(y, ext, 1e-3, 0.0, 1, tuple(mu.values()), None)
    general = SensorSideRule(problem, ext, 1e-3, True, mu)
    fast = ShiftInvariantRule(problem, ext, 1e-3, True, mu)
    for _ in range(20):
        torch.testing.assert_close(fast.step(), general.step(), rtol=0, atol=1e-14)


def test_source_admm_takes_one_batched_fft_each_way_per_iteration(fft_counter):
    ext, _, y = _problem(torch.float32, "source")
    operator_norm(ext)                  # ‖A‖ is measured once per operator (then cached)
    fft_counter.take()
    solve_tv(y, ext, iterations=7)
    assert fft_counter.take() == (7, 7)


@pytest.mark.parametrize(("convention", "basis"), FORMS)
def test_nonneg_constraint_and_stopping_rule(convention, basis):
    ext, _, y = _problem(torch.float32, convention, basis)
    free = solve_tv(y, ext, tv=1e-4, iterations=150, nonneg=False)
    assert float(free.image.min()) < 0                      # ringing without the constraint
    held = solve_tv(y, ext, tv=1e-4, iterations=150, nonneg=True)
    assert float(held.image.min()) >= 0
    stopped = solve_tv(y, ext, tv=1e-3, iterations=5000, tol=1e-3)
    assert stopped.converged and stopped.iterations < 5000
    assert stopped.relative_change[-1] < 1e-3 <= min(stopped.relative_change[:-1])
    # the stopped iterate is the one a fixed run of that many iterations gives
    fixed = solve_tv(y, ext, tv=1e-3, iterations=stopped.iterations)
    torch.testing.assert_close(fixed.image, stopped.image, rtol=0, atol=0)


def test_model_reconstructor_solvers_and_refusals():
    model = _model()
    _, _, y = _problem(torch.float32)
    auto = ModelReconstructor(model, ClassicalOptions(iterations=50))
    assert auto.solver == "admm"
    image = auto(y.numpy()).image
    assert image.shape == (1, *SENSOR) and image.dtype == np.float32
    assert np.isfinite(image).all() and image.min() >= 0
    double = ModelReconstructor(model, ClassicalOptions(iterations=50, dtype="float64"))
    np.testing.assert_allclose(double(y.numpy()).image, image, rtol=0,
                               atol=1e-4 * float(np.abs(image).max()))
    source = ModelReconstructor(_model("source"), ClassicalOptions(iterations=50))
    ext, _, _ = _problem(torch.float32, "source")
    expected = ext.crop(solve_tv(y, ext, tv=3e-4, iterations=50).image[None])[0].numpy()
    np.testing.assert_array_equal(source(y.numpy()).image, expected)
    # the removed PDHG's name runs the one solver, with a deprecation warning
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        retired = ModelReconstructor(_model("source"), ClassicalOptions(solver="pdhg",
                                                                        iterations=50))
    assert [w.category for w in caught] == [DeprecationWarning]
    assert retired.solver == "admm"
    np.testing.assert_array_equal(retired(y.numpy()).image, expected)
    si = ModelReconstructor(_model("source", "si"), ClassicalOptions(iterations=5))
    assert si.solver == "admm"                              # one kernel: either convention
    with pytest.raises(Exception, match="expects 1x20x28"):
        auto(np.zeros((1, 10, 28), np.float32))
    with pytest.raises(ConfigurationError):
        ClassicalOptions(solver="cg")


def test_unrolled_network_steps_are_the_shift_invariant_rule():
    # Le-ADMM-U unrolls ekdun.nets.tv_admm_steps (differentiable, learned μ, τ per
    # iteration, its own arithmetic so that trained networks keep their numbers): with the
    # rule's μ and τ = tv in the solver's units it is the same iteration.
    from ekdun.nets.tv_admm_steps import (
        admm_tv_context,
        admm_tv_initial_state,
        admm_tv_iteration,
        finite_difference_spectrum,
    )
    from ekdun.reconstruction.admm import normalised_problem

    ext, _, y = _problem(convention="sensor", basis="si")
    mu, tv = ShiftInvariantRule.penalties, 1e-3
    problem = normalised_problem(y, ext, tv, 0.0, 1, tuple(mu.values()), None)
    rule = ShiftInvariantRule(problem, ext, tv, True, mu)
    context = admm_tv_context(problem.y, problem.spectra[0], problem.conj[0], ext.grid_shape)
    state = admm_tv_initial_state(context)
    spectrum = finite_difference_spectrum(ext.grid_shape, torch.float64)
    for _ in range(30):
        state = admm_tv_iteration(state, context, mu["mu1"], mu["mu2"], mu["mu3"], tv, spectrum)
        x = rule.step()
        assert float((state["x"] - x).norm()) <= 1e-9 * float(x.norm())
