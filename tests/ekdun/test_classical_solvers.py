"""TV solvers for any kernel model: extended-scene operator, PDHG, closed-form ADMM (sensor- and
source-side)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ekdun.errors import ConfigurationError
from ekdun.physics.operators import EigenKernelOperator
from ekdun.reconstruction.classical import ClassicalOptions, ModelReconstructor
from ekdun.reconstruction.ek_admm import ek_admm_tv
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from ekdun.reconstruction.pdhg_tv import pdhg_tv, tv_objective
from ekdun.reconstruction.source_admm import source_admm_tv
from psfkit.forward.convolution import padded_scene_adjoint, padded_scene_forward
from psfkit.forward.geometry import centre_offset
from psfkit.forward.norm import operator_norm
from psfkit.kernelfile import KernelModel

SENSOR = (20, 28)


def _model(convention: str = "sensor", basis: str = "paper") -> KernelModel:
    rng = np.random.default_rng(1)
    n = 3 if basis == "paper" else 1
    kernels = rng.random((n, 1, 7, 9)) ** 4
    kernels -= 0.05 * rng.random(kernels.shape)          # negative lobes, as fit-pairs writes
    return KernelModel(kernels=kernels.astype(np.float32), basis=basis, convention=convention,
                       sensor_shape=SENSOR, channels=("L",))


def _problem(dtype=torch.float64, convention: str = "sensor"):
    ext = ExtendedSceneOperator.from_kernel_model(_model(convention), dtype=dtype)
    scene = torch.zeros((1, 1, *ext.grid_shape), dtype=dtype)
    scene[..., 12:30, 10:40] = 1.0
    scene[..., 20:26, 20:30] = 0.3
    y = ext.A(scene)
    noise = torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=dtype)
    return ext, scene, (y + 0.01 * y.abs().max() * noise)[0]


ADMM = {"sensor": ek_admm_tv, "source": source_admm_tv}


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
    # A solver for the other convention refuses the operator.
    with pytest.raises(ConfigurationError, match="source_admm_tv"):
        ek_admm_tv(torch.zeros((1, *SENSOR), dtype=torch.float64), ext)
    with pytest.raises(ConfigurationError, match="ek_admm_tv"):
        source_admm_tv(torch.zeros((1, *SENSOR), dtype=torch.float64),
                       ExtendedSceneOperator.from_kernel_model(_model(), dtype=torch.float64))


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_pdhg_and_admm_decrease_the_objective_and_reach_the_same_minimiser(convention):
    # No explicit norm: each solver takes ‖A‖ from the one estimator, so the same --tv is the
    # same objective (before issue 22 ADMM used the spectral gain and PDHG a power iteration:
    # TV weights 1.15-1.22x apart on DLMD models).
    ext, scene, y = _problem(convention=convention)
    tv = 3e-3
    pdhg = pdhg_tv(y, ext, tv=tv, iterations=4000, nonneg=True, track_objective=True)
    norm = pdhg.operator_norm
    weight = tv * float(y.abs().max()) * norm
    objective = np.array(pdhg.objective)
    assert objective[-1] < 0.05 * objective[0]
    # PDHG is not monotone step by step, but decreases over the run.
    checkpoints = objective[[0, 50, 300, 1000, 3999]]
    assert np.all(np.diff(checkpoints) < 0), checkpoints
    # The penalties change the speed, not the minimiser: the DLMD-tuned source-side defaults
    # need ~20000 iterations on this toy problem, these 5000.
    penalties = {"source": {"mu1": 0.5, "mu2": 0.05, "mu3": 0.05, "mu4": 0.5}}
    admm = ADMM[convention](y, ext, tv=tv, iterations=5000, nonneg=True,
                            **penalties.get(convention, {}))
    assert admm.operator_norm == norm
    a, p = admm.image[None], pdhg.image[None]
    assert float(a.min()) >= 0
    obj_admm, obj_pdhg = tv_objective(ext, a, y[None], weight), tv_objective(ext, p, y[None],
                                                                             weight)
    assert abs(obj_admm - obj_pdhg) < 1e-5 * obj_pdhg
    # Two different algorithms, one minimiser (the scene in view is what they must agree on).
    assert float((ext.crop(a) - ext.crop(p)).norm() / ext.crop(p).norm()) < 1e-4
    # The minimiser beats the true scene on the objective, and both reconstruct it.
    assert obj_pdhg <= tv_objective(ext, scene, y[None], weight)
    inside = ext.crop(scene)
    assert float((ext.crop(p) - inside).norm() / inside.norm()) < 0.25


def test_source_admm_takes_one_batched_fft_each_way_per_iteration(fft_counter):
    ext, _, y = _problem(torch.float32, "source")
    operator_norm(ext)                  # ‖A‖ is measured once per operator (then cached)
    fft_counter.take()
    source_admm_tv(y, ext, iterations=7)
    assert fft_counter.take() == (7, 7)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_nonneg_constraint_and_stopping_rule(convention):
    ext, _, y = _problem(torch.float32, convention)
    free = pdhg_tv(y, ext, tv=1e-4, iterations=150, nonneg=False)
    assert float(free.image.min()) < 0                      # ringing without the constraint
    for solve in (pdhg_tv, ADMM[convention]):
        held = solve(y, ext, tv=1e-4, iterations=150, nonneg=True)
        assert float(held.image.min()) >= 0
        stopped = solve(y, ext, tv=1e-3, iterations=5000, tol=1e-3)
        assert stopped.converged and stopped.iterations < 5000
        assert stopped.relative_change[-1] < 1e-3 <= min(stopped.relative_change[:-1])
    unconstrained = ADMM[convention](y, ext, tv=1e-4, iterations=150, nonneg=False)
    assert float(unconstrained.image.min()) < 0


def test_model_reconstructor_solvers_and_refusals():
    model = _model()
    _, _, y = _problem(torch.float32)
    auto = ModelReconstructor(model, ClassicalOptions(iterations=50))
    assert auto.solver == "admm" and auto.extended
    image = auto(y.numpy()).image
    assert image.shape == (1, *SENSOR) and image.dtype == np.float32
    assert np.isfinite(image).all() and image.min() >= 0
    double = ModelReconstructor(model, ClassicalOptions(iterations=50, dtype="float64"))
    np.testing.assert_allclose(double(y.numpy()).image, image, rtol=0,
                               atol=1e-4 * float(np.abs(image).max()))
    source = ModelReconstructor(_model("source"), ClassicalOptions(iterations=50))
    assert source.solver == "admm" and source.extended
    ext, _, _ = _problem(torch.float32, "source")
    expected = ext.crop(source_admm_tv(y, ext, tv=3e-4, iterations=50).image[None])[0].numpy()
    np.testing.assert_array_equal(source(y.numpy()).image, expected)
    narrow = ModelReconstructor(_model("source"), ClassicalOptions(solver="pdhg", extended=False,
                                                                   iterations=5))
    assert not narrow.extended and np.isfinite(narrow(y.numpy()).image).all()
    with pytest.raises(ConfigurationError, match="padded grid"):
        ModelReconstructor(model, ClassicalOptions(solver="admm", extended=False))
    si = ModelReconstructor(_model("source", "si"), ClassicalOptions(iterations=5))
    assert si.solver == "admm"                              # one kernel: either convention
    with pytest.raises(Exception, match="expects 1x20x28"):
        auto(np.zeros((1, 10, 28), np.float32))
    with pytest.raises(ConfigurationError):
        ClassicalOptions(solver="cg")
