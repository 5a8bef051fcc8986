"""Forward-model fits from (scene, measurement) pairs: operator algebra, recovery of known
kernels, per-pair scales, and the real DiffuserCam Mirflickr pairs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.fitting.pairs.batches import PairBatches
from psfkit.fitting.pairs.constraints import auto_support, projected_newton
from psfkit.fitting.pairs.fit import (
    KernelSpaceOperator,
    PairFitOptions,
    downsample_pairs,
    fit_pairs,
    leave_one_out,
    predict,
    relative_errors,
    upsampled_kernels,
)
from psfkit.fitting.pairs.options import NEWTON_ITERATIONS, NEWTON_TOLERANCE
from psfkit.fitting.pairs.solver import solve_kernels
from psfkit.forward.kernelfile import KernelModel
from psfkit.forward.weights import get_basis
from tests.helpers.pairs import kkt_residual


def _scenes(rng: np.random.Generator, n: int, c: int, h: int, w: int) -> np.ndarray:
    """Smooth-ish random scenes (natural images are not white noise)."""
    from scipy.ndimage import gaussian_filter

    x = rng.random((n, c, h, w))
    return np.stack([[gaussian_filter(ch, 0.7) for ch in im] for im in x]).astype(np.float64)


def _kernels(rng: np.random.Generator, k: int, c: int, h: int, w: int) -> np.ndarray:
    base = rng.random((1, c, h, w)) ** 4
    out = np.repeat(base, k, axis=0)
    out[1:] += 0.5 * rng.random((k - 1, c, h, w)) ** 4
    return out / out[0].sum(axis=(-2, -1), keepdims=True)


@pytest.mark.parametrize(("basis", "convention"),
                         [("si", "sensor"), ("paper", "sensor"), ("paper", "source"),
                          ("paper+odd", "sensor")])
def test_kernel_space_operator_is_adjoint(basis: str, convention: str) -> None:
    rng = np.random.default_rng(0)
    x = torch.as_tensor(_scenes(rng, 3, 2, 10, 13))
    op = KernelSpaceOperator(x, basis, convention, (7, 9))
    k = torch.as_tensor(rng.standard_normal((get_basis(basis).n_kernels, 2, 7, 9)))
    r = torch.as_tensor(rng.standard_normal((3, 2, 10, 13)))
    lhs = float((op.forward(k) * r).sum())
    rhs = float((k * op.adjoint(r)).sum())
    assert abs(lhs - rhs) <= 1e-12 * max(abs(lhs), 1.0)


@pytest.mark.parametrize(("basis", "convention"), [("si", "sensor"), ("paper", "sensor"),
                                                   ("paper", "source")])
@pytest.mark.parametrize("shape", [(12, 16), (13, 17), (11, 10)])
def test_kernel_space_forward_is_the_ekdun_operator(basis: str, convention: str,
                                                    shape: tuple[int, int]) -> None:
    """Same operator as ekdun's (on its 2× grid), although the fit runs on a smaller grid."""
    rng = np.random.default_rng(1)
    x = _scenes(rng, 2, 3, *shape)
    kernels = _kernels(rng, get_basis(basis).n_kernels, 3, *shape).astype(np.float32)
    kernels[..., 0, :] += 0.5                    # mass at the support's edges: wrap-around shows
    kernels[..., :, -1] += 0.5
    model = KernelModel(kernels=kernels, basis=basis, convention=convention,
                        sensor_shape=shape, channels=("R", "G", "B"))
    op = KernelSpaceOperator(torch.as_tensor(x), basis, convention, shape)
    assert op.grid[0] < 2 * shape[0] and op.grid[1] < 2 * shape[1]
    ours = op.forward(torch.as_tensor(kernels, dtype=torch.float64)).numpy()
    theirs = predict(model, x.astype(np.float32))
    assert np.abs(ours - theirs).max() <= 1e-5 * np.abs(theirs).max()


def test_shift_invariant_fit_recovers_a_known_psf_and_predicts_held_out_pairs() -> None:
    rng = np.random.default_rng(2)
    truth = _kernels(rng, 1, 1, 16, 20)
    x = _scenes(rng, 5, 1, 16, 20)
    model = KernelModel(kernels=truth.astype(np.float32), basis="si", convention="sensor",
                        sensor_shape=(16, 20), channels=("L",))
    y = predict(model, x.astype(np.float32)).astype(np.float64)
    options = PairFitOptions(basis="si", tikhonov=1e-9, iterations=400, tolerance=1e-10,
                             fit_scale=False)
    fit = fit_pairs(x[:4], y[:4], options, dtype=torch.float64)
    assert fit.training_error.max() < 1e-4
    held_out = relative_errors(predict(fit.kernel_model(), x[4:].astype(np.float32)), y[4:])
    assert held_out["raw"][0] < 2e-3
    # a fit from zero kernels is a zero model: 100 % error, so the test can fail
    assert relative_errors(np.zeros_like(y[4:]), y[4:])["raw"][0] == pytest.approx(1.0)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_eigen_kernel_fit_beats_shift_invariant_on_eigen_kernel_data(convention: str) -> None:
    rng = np.random.default_rng(3)
    truth = _kernels(rng, 3, 1, 16, 20)
    x = _scenes(rng, 7, 1, 16, 20)
    model = KernelModel(kernels=truth.astype(np.float32), basis="paper",
                        convention=convention, sensor_shape=(16, 20), channels=("L",))
    y = predict(model, x.astype(np.float32)).astype(np.float64)
    common = dict(convention=convention, tikhonov=1e-8, difference=0.0, iterations=600,
                  tolerance=1e-10, fit_scale=False)
    ek = fit_pairs(x[:6], y[:6], PairFitOptions(basis="paper", **common), dtype=torch.float64)
    si = fit_pairs(x[:6], y[:6], PairFitOptions(basis="si", **common), dtype=torch.float64)
    err_ek = relative_errors(predict(ek.kernel_model(), x[6:].astype(np.float32)), y[6:])["raw"]
    err_si = relative_errors(predict(si.kernel_model(), x[6:].astype(np.float32)), y[6:])["raw"]
    assert err_ek[0] < 0.02
    assert err_ek[0] < 0.2 * err_si[0]


def test_per_pair_scales_are_recovered() -> None:
    rng = np.random.default_rng(4)
    truth = _kernels(rng, 1, 1, 12, 12)
    x = _scenes(rng, 4, 1, 12, 12)
    model = KernelModel(kernels=truth.astype(np.float32), basis="si", convention="sensor",
                        sensor_shape=(12, 12), channels=("L",))
    gains = np.array([0.8, 1.0, 1.1, 1.25])
    y = predict(model, x.astype(np.float32)).astype(np.float64) * gains[:, None, None, None]
    fit = fit_pairs(x, y, PairFitOptions(tikhonov=1e-9, iterations=300, tolerance=1e-10,
                                         rounds=8), dtype=torch.float64)
    ratio = fit.scales / (gains / gains.mean())
    assert np.abs(ratio - ratio.mean()).max() < 5e-3
    assert fit.training_error.max() < 5e-3


def test_downsample_pairs_averages_blocks() -> None:
    a = np.arange(2 * 1 * 12 * 19, dtype=np.float32).reshape(2, 1, 12, 19)
    s, m = downsample_pairs(a, a + 1, 3)
    assert s.shape == (2, 1, 4, 6)
    assert s[0, 0, 0, 0] == pytest.approx(a[0, 0, :3, :3].mean())
    assert np.allclose(m, s + 1)
    with pytest.raises(InvalidInputError, match="too few pixels"):
        downsample_pairs(a, a, 5)


@pytest.mark.parametrize("factor", [2, 3])
@pytest.mark.parametrize("shape", [(31, 47), (30, 45)])
def test_upsampled_kernels_keep_each_binned_pixel_where_it_acts(factor: int,
                                                                shape: tuple[int, int]) -> None:
    """A binned pixel at offset ``(a, b)`` from the binned origin acts at fine offsets
    ``factor·(a, b)`` (within half a pixel for an even factor): its energy lands there, whole,
    in the unbinned grid's centred origin convention."""
    coarse_shape = (shape[0] // factor, shape[1] // factor)
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    for a, b in ((0, 0), (2, -3), (-1, 4)):
        coarse = torch.zeros((1, 1, *coarse_shape), dtype=torch.float64)
        coarse[0, 0, coarse_shape[0] // 2 + a, coarse_shape[1] // 2 + b] = 2.0
        fine = upsampled_kernels(coarse, factor, shape)[0, 0].numpy()
        assert fine.shape == shape and fine.sum() == pytest.approx(2.0 / factor**2 * factor**2)
        centroid = ((fine * rows).sum() / fine.sum() - shape[0] // 2,
                    (fine * cols).sum() / fine.sum() - shape[1] // 2)
        assert np.allclose(centroid, (factor * a, factor * b), atol=0.5 if factor % 2 == 0
                           else 1e-12), (a, b, centroid)


def test_bad_options_and_shapes() -> None:
    with pytest.raises(ConfigurationError):
        PairFitOptions(convention="middle")
    with pytest.raises(ConfigurationError):
        PairFitOptions(tikhonov=-1)
    with pytest.raises(ConfigurationError, match="support"):
        PairFitOptions(support="circle")
    x = np.zeros((2, 1, 8, 8), np.float32)
    with pytest.raises(InvalidInputError, match="must both be"):
        fit_pairs(x, x[:1])
    with pytest.raises(InvalidInputError, match="at least two"):
        leave_one_out(x[:1], x[:1], PairFitOptions())


@pytest.mark.parametrize("preconditioned", [False, True])
def test_projected_newton_is_scipy_nnls(preconditioned: bool) -> None:
    """On an ill-conditioned least squares with active bounds, the projected Newton-CG
    minimiser is scipy's active-set NNLS solution, per channel."""
    from scipy.optimize import nnls

    rng = np.random.default_rng(3)
    shape = (2, 2, 3, 3)                                  # (K, C, Hk, Wk): 18 unknowns per channel
    n = int(np.prod(shape[:1] + shape[2:]))
    mats = [rng.normal(size=(40, n)) @ np.diag(np.logspace(0, -2, n)) for _ in range(2)]
    ys = [rng.normal(size=40) for _ in range(2)]

    def per_channel(fn, k: torch.Tensor) -> torch.Tensor:
        out = torch.empty_like(k)
        for c in range(k.shape[1]):
            out[:, c] = torch.as_tensor(fn(c, k[:, c].reshape(-1).numpy())).reshape(
                k[:, c].shape)
        return out

    def normal(k: torch.Tensor) -> torch.Tensor:
        return per_channel(lambda c, v: mats[c].T @ (mats[c] @ v), k)

    rhs = per_channel(lambda c, v: mats[c].T @ ys[c], torch.zeros(shape, dtype=torch.float64))
    diag = [np.sum(m * m, axis=0) for m in mats]          # Jacobi: SPD, a fair preconditioner
    precondition = (lambda r: per_channel(lambda c, v: v / diag[c], r)) if preconditioned \
        else None
    got, info = projected_newton(normal, rhs, torch.zeros(shape, dtype=torch.float64),
                                 precondition, iterations=100, cg_iterations=n,
                                 tolerance=1e-12)
    for c in range(2):
        want, _ = nnls(mats[c], ys[c])
        assert (want == 0).sum() >= 3                     # bounds are active
        np.testing.assert_allclose(got[:, c].reshape(-1).numpy(), want, atol=1e-8)
    assert got.min() >= 0 and info["kkt_residual"] < 1e-12
    assert float(kkt_residual(normal, rhs, got).max()) == pytest.approx(info["kkt_residual"])


def test_auto_support_is_the_footprint_of_the_psf() -> None:
    base = np.zeros((3, 40, 40))
    base[:, 10:20, 12:30] = 1.0
    mask = auto_support(base, threshold=0.1, smoothing=1.0, dilation=2)
    # smoothing widens it by ~1 pixel (at 10 % of the maximum), the dilation by 2 more
    assert mask[10:20, 12:30].all() and mask[15, 9] and mask[7, 20]
    assert not mask[15, 7] and not mask[5, 20] and not mask[0, 0]


def _tiny_camera() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``tests/conftest.py``'s tiny eigen-kernel camera (non-negative caustic kernels, sensor
    convention) and 8 dead-leaves scenes with their exact measurements, float64."""
    from ekdun.data.deadleaves import dead_leaves
    from research.synthetic import caustic_psf

    shape = (16, 16)
    psf = caustic_psf(shape, 3, seed=3)
    kernels = np.stack([psf, 0.8 * np.roll(psf, 1, axis=1), 0.8 * np.roll(psf, 1, axis=2)])
    x = np.stack([dead_leaves(shape, i) for i in range(8)]).astype(np.float32)
    y = predict(KernelModel(kernels=kernels, sensor_shape=shape), x)
    return kernels.astype(np.float64), x.astype(np.float64), y.astype(np.float64)


@pytest.mark.parametrize("noise", [0.0, 0.03])
def test_constrained_fit_recovers_non_negative_kernels(noise: float) -> None:
    """Exact data: both fits find the kernels. Noisy data (3 % of the signal's spread): the
    unconstrained fit's kernels are off by more than their own size, with hundreds of negative
    pixels; non-negativity halves the kernel error and the held-out error (measured 1.16 →
    0.57 and 0.0115 → 0.0072)."""
    truth, x, y = _tiny_camera()
    rng = np.random.default_rng(0)
    noisy = y + noise * y.std() * rng.standard_normal(y.shape)
    kernel_error, held_out = {}, {}
    for nonneg in (False, True):
        options = PairFitOptions(basis="paper", convention="sensor", tikhonov=1e-6,
                                 difference=0.0, iterations=300, tolerance=1e-10,
                                 fit_scale=False, nonneg=nonneg, projected_iterations=500)
        fit = fit_pairs(x[:7], noisy[:7], options, dtype=torch.float64)
        if nonneg:
            assert fit.physics()["negative_pixels"] == 0
            assert fit.history[-1]["method"] == "projected-newton-cg"
        kernel_error[nonneg] = np.linalg.norm(fit.kernels - truth) / np.linalg.norm(truth)
        held_out[nonneg] = relative_errors(predict(fit.kernel_model(), x[7:]), y[7:])["raw"][0]
    if noise == 0:
        assert kernel_error[True] < 1e-3 and held_out[True] < 1e-4
    else:
        assert kernel_error[False] > 1.0
        assert kernel_error[True] < 0.6 * kernel_error[False]
        assert held_out[True] < 0.7 * held_out[False]


def _dense_system(normal, rhs: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The normal matrix ``(C, n, n)`` and right-hand side ``(C, n)`` of a per-channel
    operator on ``(K, C, Hk, Wk)`` kernels, column by column (n = K·Hk·Wk)."""
    k, c, h, w = rhs.shape
    n = k * h * w
    columns = np.empty((c, n, n))
    for j in range(n):
        e = torch.zeros(k * h * w, dtype=rhs.dtype)
        e[j] = 1.0
        out = normal(e.reshape(k, 1, h, w).expand(k, c, h, w).contiguous())
        columns[:, :, j] = out.permute(1, 0, 2, 3).reshape(c, n).numpy()
    return columns, rhs.permute(1, 0, 2, 3).reshape(c, n).numpy()


def _dense_nnls(matrix: np.ndarray, rhs: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """``argmin ½kᵀNk − rhsᵀk`` over ``k ≥ 0``, ``k = 0`` outside ``inside``, by scipy's
    active-set NNLS on the Cholesky factor (``½‖Lᵀk − L⁻¹rhs‖²`` is the same objective up to
    a constant)."""
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import nnls

    sub = matrix[np.ix_(inside, inside)]
    upper = cholesky(0.5 * (sub + sub.T))                 # sub = UᵀU
    got = np.zeros(len(rhs))
    got[inside] = nnls(upper, solve_triangular(upper, rhs[inside], trans="T"),
                       maxiter=20 * len(sub))[0]
    return got


@pytest.mark.parametrize("with_support", [False, True])
def test_newton_solver_is_the_non_negative_least_squares(with_support: bool) -> None:
    """The non-negative solve (projected Newton-CG, its CG on float32 products) reaches the
    non-negative least squares (KKT residual below its tolerance): the minimiser that scipy's
    active-set NNLS finds on the dense normal equations of the same fit (an independent
    method), within and outside a support."""
    _truth, x, y = _tiny_camera()
    noisy = y + 0.03 * y.std() * np.random.default_rng(1).standard_normal(y.shape)
    mask = np.zeros((16, 16), bool)
    mask[2:14, 3:15] = True
    common = dict(basis="paper", convention="sensor", iterations=300, tolerance=1e-10,
                  fit_scale=False, support="mask" if with_support else "none", tikhonov=0.0,
                  difference=0.0)
    extra = {"support_mask": mask} if with_support else {}
    newton = fit_pairs(x, noisy, PairFitOptions(**common), dtype=torch.float64, **extra)
    step = newton.history[-1]
    assert step["method"] == "projected-newton-cg" and step["kkt_residual"] < NEWTON_TOLERANCE
    assert step["converged"] and not step["stalled"]
    assert step["float32_passes"] > 0                  # the Newton steps' CG ran in float32
    assert step["iterations"] <= 50 and newton.kernels.min() >= 0
    if with_support:
        assert np.abs(newton.kernels[..., ~mask]).max() == 0
    batches = PairBatches(x, "paper", "sensor", (16, 16))
    _start, _, system = solve_kernels(batches, noisy, max_iterations=0)
    matrix, rhs = _dense_system(system["normal"], system["rhs"])
    inside = np.broadcast_to(mask if with_support else np.ones_like(mask), (3, 16, 16))
    kernels = newton.kernels.astype(np.float64)
    for c in range(rhs.shape[0]):
        want = _dense_nnls(matrix[c], rhs[c], inside.reshape(-1))
        assert (want[inside.reshape(-1)] == 0).sum() > 10        # bounds are active
        got = kernels[:, c].reshape(-1)
        rel = np.linalg.norm(got - want) / np.linalg.norm(want)
        assert rel < 2e-3, rel

        def objective(k: np.ndarray, c: int = c) -> float:
            return float(0.5 * k @ matrix[c] @ k - rhs[c] @ k)

        assert objective(got) <= objective(want) + 1e-6 * abs(objective(want))


def test_support_without_nonnegativity_is_the_exact_restricted_least_squares() -> None:
    """``--no-nonneg`` with a support: conjugate gradients restricted to it give the least
    squares over the supported pixels (a dense solve of the same normal equations), zero
    outside, with their negative lobes."""
    _truth, x, y = _tiny_camera()
    noisy = y + 0.03 * y.std() * np.random.default_rng(1).standard_normal(y.shape)
    mask = np.zeros((16, 16), bool)
    mask[2:14, 3:15] = True
    fit = fit_pairs(x, noisy, PairFitOptions(basis="paper", convention="sensor", tikhonov=0.0,
                                             difference=0.0, tolerance=1e-10, iterations=500,
                                             fit_scale=False, nonneg=False, support="mask"),
                    dtype=torch.float64, support_mask=mask)
    step = fit.history[-1]
    assert step["method"] == "pcg-frequency-gram" and step["restricted_to_support"]
    assert step["converged"] and step["relative_residual"] < 1e-9
    assert np.abs(fit.kernels[..., ~mask]).max() == 0 and fit.kernels.min() < 0
    batches = PairBatches(x, "paper", "sensor", (16, 16))
    _start, _, system = solve_kernels(batches, noisy, max_iterations=0)
    matrix, rhs = _dense_system(system["normal"], system["rhs"])
    inside = np.broadcast_to(mask, (3, 16, 16)).reshape(-1)
    for c in range(rhs.shape[0]):
        want = np.linalg.solve(matrix[c][np.ix_(inside, inside)], rhs[c][inside])
        got = fit.kernels[:, c].reshape(-1)[inside].astype(np.float64)
        assert np.linalg.norm(got - want) / np.linalg.norm(want) < 1e-5


def test_constrained_solver_follows_from_the_constraints() -> None:
    """One solver per problem (issue 44): projected Newton for non-negativity (with or without
    a support), conjugate gradients otherwise; no choice of solver, no energy constraint."""
    fields = PairFitOptions.__dataclass_fields__
    assert "nonneg_solver" not in fields and "energy" not in fields
    assert PairFitOptions().solver == "newton"
    assert PairFitOptions().final_projected_iterations == NEWTON_ITERATIONS
    assert PairFitOptions(support="auto").solver == "newton"
    assert PairFitOptions(nonneg=False, support="auto").solver == "cg"
    assert PairFitOptions(nonneg=False).solver == "cg"
    assert not PairFitOptions(nonneg=False).constrained


def test_support_constraint_holds_and_is_recorded() -> None:
    _truth, x, y = _tiny_camera()
    common = dict(basis="paper", convention="sensor", tikhonov=1e-3, difference=0.1,
                  iterations=50, fit_scale=False)
    mask = np.zeros((16, 16), bool)
    mask[2:14, 3:15] = True
    fit = fit_pairs(x, y, PairFitOptions(support="mask", **common),
                    dtype=torch.float64, support_mask=mask)
    assert np.abs(fit.kernels[..., ~mask]).max() == 0 and fit.kernels.min() >= 0
    physics = fit.physics()
    assert physics["constraints"] == {"nonneg": True, "support": "mask"}
    assert physics["support_fraction"] <= mask.mean()
    # the kernels are handed over in float32 (docs/architecture.md): their sums agree to its
    # rounding
    np.testing.assert_allclose(physics["energy"], fit.kernels.sum(axis=(-2, -1)), rtol=1e-6)
    with pytest.raises(InvalidInputError, match="support mask"):
        fit_pairs(x, y, PairFitOptions(support="mask", **common))
    with pytest.raises(InvalidInputError, match="16x16"):
        fit_pairs(x, y, PairFitOptions(support="mask", **common), support_mask=mask[1:])


def test_dlmd_held_out_error_eigen_kernel_vs_shift_invariant(real_data) -> None:
    """Real DiffuserCam Mirflickr pairs (no PSF available): leave-one-out prediction error of
    the eigen-kernel model against the best shift-invariant PSF, and of the default
    (non-negative) fits against the unconstrained ones, at 1/8 resolution for CI time
    (benchmarks/bench_fit_pairs.py reports full and half resolution; the 1/4-resolution fits
    are the golden files)."""
    from psfkit.io import read_pairs

    torch.set_num_threads(1)
    x, y = downsample_pairs(*read_pairs(real_data("dlmd_mirflickr")).load_all(), 8)
    # Seven pairs do not determine Kv - Kbase and Kh - Kbase: without the difference prior
    # (the default since issue 23, which biases well-determined fits) the eigen-kernel fit
    # overfits (held-out 0.129 scaled, 0.085 unconstrained); with --difference 1 it is 0.0535.
    ek_options = dict(basis="paper", convention="source", difference=1.0)
    # the weights given, as measured before issue 43 (its automatic choice, nested in every
    # fold, is tested in test_pairs_select.py)
    si = leave_one_out(x, y, PairFitOptions(basis="si", tikhonov=0.0))
    ek = leave_one_out(x, y, PairFitOptions(**ek_options))
    si_free = leave_one_out(x, y, PairFitOptions(basis="si", tikhonov=0.0, nonneg=False))
    ek_free = leave_one_out(x, y, PairFitOptions(**ek_options, nonneg=False))
    print("DLMD 1/8 res held-out mean (raw/scaled): si", si["mean_raw"], si["mean_scaled"],
          "ek", ek["mean_raw"], ek["mean_scaled"], "unconstrained si", si_free["mean_raw"],
          si_free["mean_scaled"], "ek", ek_free["mean_raw"], ek_free["mean_scaled"])
    assert si["mean_scaled"] < 0.08            # a real PSF was found (a wrong one gives ~1)
    # Measured at 1/8: 0.0527 vs 0.0634 scaled (ratio 0.83) and 0.0768 vs 0.0862 raw (0.89);
    # at 1/4: 0.0531 vs 0.0637 (0.83) and 0.0748 vs 0.0865 (0.86). Better, but short of the
    # issue's 0.75 target with 7 pairs (see docs/forward-models.md).
    assert ek["mean_scaled"] <= 0.9 * si["mean_scaled"]
    assert ek["mean_raw"] <= 0.95 * si["mean_raw"]
    # Non-negativity helps held out: measured at 1/8 si 0.0634 vs 0.0645 scaled, 0.0862 vs
    # 0.0871 raw; ek 0.0527 vs 0.0540, 0.0768 vs 0.0775 (gains 7e-4 .. 1.4e-3; at 1/4 1.0e-3
    # .. 2.2e-3). The errors move by at most 3e-5 between threads or for a one-ulp change of
    # the inputs (tests/e2e/golden/tolerances.json), so a gain of 2e-4 is required, not merely
    # no loss.
    for constrained, free in ((si, si_free), (ek, ek_free)):
        for kind in ("mean_raw", "mean_scaled"):
            assert constrained[kind] < free[kind] - 2e-4, (kind, constrained[kind], free[kind])
    fit = fit_pairs(x, y, PairFitOptions(**ek_options))
    physics = fit.physics()
    assert physics["negative_pixels"] == 0 and physics["nonfinite_pixels"] == 0
    assert fit.kernels.min() == 0 and np.isfinite(fit.kernels).all()
    unconstrained = fit_pairs(x, y, PairFitOptions(**ek_options, nonneg=False))
    assert (unconstrained.kernels < 0).mean() > 0.2     # the lobes the constraint removes
