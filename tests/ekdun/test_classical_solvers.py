"""TV solvers for any kernel model: extended-scene operator, PDHG, closed-form EK-ADMM."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ekdun.errors import ConfigurationError
from ekdun.physics.operators import EigenKernelOperator
from ekdun.reconstruction.classical import ClassicalOptions, ModelReconstructor
from ekdun.reconstruction.ek_admm import ek_admm_tv
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from ekdun.reconstruction.pdhg_tv import operator_norm, pdhg_tv, tv_objective
from psfkit.kernelfile import KernelModel

SENSOR = (20, 28)


def _model(convention: str = "sensor", basis: str = "paper") -> KernelModel:
    rng = np.random.default_rng(1)
    n = 3 if basis == "paper" else 1
    kernels = rng.random((n, 1, 7, 9)) ** 4
    kernels -= 0.05 * rng.random(kernels.shape)          # negative lobes, as fit-pairs writes
    return KernelModel(kernels=kernels.astype(np.float32), basis=basis, convention=convention,
                       sensor_shape=SENSOR, channels=("L",))


def _problem(dtype=torch.float64):
    op = EigenKernelOperator.from_kernel_model(_model(), dtype=dtype).prepare()
    ext = ExtendedSceneOperator(op)
    scene = torch.zeros((1, 1, *ext.grid_shape), dtype=dtype)
    scene[..., 12:30, 10:40] = 1.0
    scene[..., 20:26, 20:30] = 0.3
    y = ext.A(scene)
    noise = torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=dtype)
    return ext, scene, (y + 0.01 * y.abs().max() * noise)[0]


def test_extended_operator_matches_the_sensor_sized_model_and_is_adjoint():
    op = EigenKernelOperator.from_kernel_model(_model(), dtype=torch.float64).prepare()
    ext = ExtendedSceneOperator(op)
    g = torch.Generator().manual_seed(3)
    x = torch.randn((2, 1, *SENSOR), generator=g, dtype=torch.float64)
    torch.testing.assert_close(ext.A(ext.pad(x)), op.A(x), rtol=1e-12, atol=1e-12)
    big = torch.randn((2, 1, *ext.grid_shape), generator=g, dtype=torch.float64)
    y = torch.randn((2, 1, *SENSOR), generator=g, dtype=torch.float64)
    lhs, rhs = float((ext.A(big) * y).sum()), float((big * ext.A_adjoint(y)).sum())
    assert abs(lhs - rhs) < 1e-10 * abs(lhs)
    with pytest.raises(ConfigurationError):
        ExtendedSceneOperator(EigenKernelOperator.from_kernel_model(
            _model("source"), dtype=torch.float64).prepare())


def test_pdhg_and_ek_admm_decrease_the_objective_and_reach_the_same_minimiser():
    ext, scene, y = _problem()
    norm = 1.05 * operator_norm(ext, (1, 1, *ext.grid_shape), torch.float64, iterations=50)
    tv = 3e-3
    weight = tv * float(y.abs().max()) * norm
    pdhg = pdhg_tv(y, ext, tv=tv, iterations=4000, nonneg=True, norm=norm,
                   track_objective=True)
    objective = np.array(pdhg.objective)
    assert objective[-1] < 0.05 * objective[0]
    # PDHG is not monotone step by step, but decreases over the run.
    checkpoints = objective[[0, 50, 300, 1000, 3999]]
    assert np.all(np.diff(checkpoints) < 0), checkpoints
    admm = ek_admm_tv(y, ext, tv=tv, iterations=5000, nonneg=True, norm=norm)
    a, p = admm.image[None], pdhg.image[None]
    obj_admm, obj_pdhg = tv_objective(ext, a, y[None], weight), tv_objective(ext, p, y[None],
                                                                             weight)
    assert abs(obj_admm - obj_pdhg) < 1e-5 * obj_pdhg
    # Two different algorithms, one minimiser (the scene in view is what they must agree on).
    assert float((ext.crop(a) - ext.crop(p)).norm() / ext.crop(p).norm()) < 1e-4
    # The minimiser beats the true scene on the objective, and both reconstruct it.
    assert obj_pdhg <= tv_objective(ext, scene, y[None], weight)
    inside = ext.crop(scene)
    assert float((ext.crop(p) - inside).norm() / inside.norm()) < 0.25


def test_nonneg_constraint_and_stopping_rule():
    ext, _, y = _problem(torch.float32)
    free = pdhg_tv(y, ext, tv=1e-4, iterations=150, nonneg=False)
    assert float(free.image.min()) < 0                      # ringing without the constraint
    for solve in (pdhg_tv, ek_admm_tv):
        held = solve(y, ext, tv=1e-4, iterations=150, nonneg=True)
        assert float(held.image.min()) >= 0
        stopped = solve(y, ext, tv=1e-3, iterations=5000, tol=1e-3)
        assert stopped.converged and stopped.iterations < 5000
        assert stopped.relative_change[-1] < 1e-3 <= min(stopped.relative_change[:-1])


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
    source = ModelReconstructor(_model("source"), ClassicalOptions(iterations=5))
    assert source.solver == "pdhg" and not source.extended
    assert np.isfinite(source(y.numpy()).image).all()
    with pytest.raises(ConfigurationError, match="source-side"):
        ModelReconstructor(_model("source"), ClassicalOptions(solver="pdhg", extended=True))
    with pytest.raises(ConfigurationError, match="source-side"):
        ModelReconstructor(_model("source"), ClassicalOptions(solver="admm"))
    si = ModelReconstructor(_model("source", "si"), ClassicalOptions(iterations=5))
    assert si.solver == "admm"                              # one kernel: either convention
    with pytest.raises(Exception, match="expects 1x20x28"):
        auto(np.zeros((1, 10, 28), np.float32))
    with pytest.raises(ConfigurationError):
        ClassicalOptions(solver="cg")
