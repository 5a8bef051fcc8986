"""The exact pairs solver (issue 23 items 5 and 6): per-frequency Gram blocks, streaming
normal operator, PCG to a tolerance, and recovery of known eigen-kernels by fit-pairs'
defaults (the earlier defaults' priors biased them)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from psfkit.fitting.pairs.batches import BATCH_BYTES, DEFAULT_BATCH, PairBatches, auto_batch_size
from psfkit.fitting.pairs.constraints import (
    STALL_STEPS,
    _armijo_step,
    _cheap_products_too_coarse,
    projected_newton,
)
from psfkit.fitting.pairs.fit import START_TOLERANCE, PairFitOptions, fit_pairs, predict
from psfkit.fitting.pairs.gram import FrequencyGram
from psfkit.fitting.pairs.solver import regularised_normal, solve_kernels
from psfkit.forward.convolution import kernel_spectra
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.kernel_space import KernelSpaceOperator
from psfkit.forward.kernelfile import KernelModel
from research.compare.statistics import normalized_correlation as ncc
from tests.helpers.operators import extract_kernel
from tests.helpers.pairs import kkt_residual


def known_eigen_kernels(shape: tuple[int, int] = (32, 32), channels: int = 3) -> np.ndarray:
    """Non-negative caustic kernels whose corrections are a vertical / horizontal stretch of
    the base (the astigmatism the bench shows), ``(3, C, H, W)`` float64."""
    from scipy.ndimage import affine_transform

    from research.synthetic import caustic_psf

    base = caustic_psf(shape, channels, seed=5).astype(np.float64)
    centre = np.array([shape[0] // 2, shape[1] // 2], dtype=np.float64)

    def stretched(scale: tuple[float, float]) -> np.ndarray:
        matrix = np.diag([1 / scale[0], 1 / scale[1]])
        offset = centre - matrix @ centre
        out = np.stack([affine_transform(c, matrix, offset, order=1) for c in base])
        return out * 0.9 / out.sum(axis=(-2, -1), keepdims=True)

    return np.stack([base, stretched((1.12, 1.0)), stretched((1.0, 1.12))])


def bench_scenes(n: int, shape: tuple[int, int] = (32, 32), seed: int = 0) -> np.ndarray:
    """Scenes of the virtual bench's own distribution (dead leaves + natural crops)."""
    from ekdun.data.virtual_bench import VirtualBenchSpec, make_scenes

    spec = VirtualBenchSpec(sensor_shape=shape, n_train=n, n_test=1, seed=seed)
    return make_scenes(spec, "train").astype(np.float64)


def _metrics(fitted: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    return {"base": ncc(fitted[0], truth[0]),
            "v": ncc(fitted[1] - fitted[0], truth[1] - truth[0]),
            "h": ncc(fitted[2] - fitted[0], truth[2] - truth[0]),
            "error": float(np.linalg.norm(fitted - truth) / np.linalg.norm(truth))}


# --------------------------------------------------------------------------- the uncropped problem
# Test-only: the closed form of the uncropped, whole-grid problem (source side and SI), the
# exact meaning of the Gram blocks that the product uses only as a preconditioner.


def solve_full(gram: FrequencyGram, rhs_spectra: torch.Tensor, tikhonov: float = 0.0,
               difference: float = 0.0) -> torch.Tensor:
    r"""The closed-form least squares of the **uncropped** problem on the whole grid:
    :math:`\hat K(\omega) = [G(\omega) + \lambda + \mu D]^{-1}\,\hat r(\omega)` with
    ``rhs_spectra`` ``(K, C, PH, PW//2+1)`` = :math:`\sum_i s_i\overline{\hat S_{ik}}\hat
    y_i` of whole-grid measurements. Exact for the source side and SI; returns the kernels
    ``(K, C, PH, PW)`` with their origin at index ``(0, 0)`` of the grid."""
    inv = gram.inverse(tikhonov, difference)
    r = rhs_spectra.to(torch.complex128).permute(1, 2, 3, 0)          # (C, F..., K)
    k_hat = torch.einsum("cuvkl,cuvl->kcuv", inv, r)
    return irfft2(k_hat, gram.grid)


def uncropped_measurements(batches: PairBatches, kernels: torch.Tensor, start: int, stop: int
                           ) -> torch.Tensor:
    """The whole-grid (uncropped) model output of pairs ``start:stop`` for ``kernels``
    ``(K, C, Hk, Wk)`` (source side / SI)."""
    op = batches.operator(start, stop)
    spectra = kernel_spectra(kernels.to(op.scene_spectra.real.dtype), batches.grid)
    total = (op.scene_spectra * spectra[None]).sum(dim=1)
    return irfft2(total, batches.grid)


def rhs_spectra_full(batches: PairBatches, full_measurements: torch.Tensor) -> torch.Tensor:
    """``Σ_i s_i conj(Ŝ_ik) ŷ_i`` of whole-grid measurements ``(N, C, PH, PW)``."""
    out = None
    for start, stop, op, s in batches.batches():
        y_hat = rfft2(full_measurements[start:stop].to(op.scene_spectra.real.dtype))
        term = (op.scene_spectra.conj() * (y_hat * s[:, None, None, None])[:, None]).sum(0)
        out = term if out is None else out + term
    assert out is not None
    return out


@pytest.fixture(scope="module")
def scenes() -> np.ndarray:
    return bench_scenes(40)


@pytest.mark.parametrize("basis", ["si", "paper"])
def test_gram_solves_the_uncropped_problem_in_closed_form(scenes: np.ndarray,
                                                          basis: str) -> None:
    """Source side, whole linear convolution measured, kernels on the whole grid: one K×K
    solve per frequency gives back the kernels exactly (noise-free)."""
    truth = known_eigen_kernels()[: 1 if basis == "si" else 3]
    batches = PairBatches(scenes, basis, "source", (32, 32), batch_size=7)
    gram = batches.gram()
    k = torch.as_tensor(truth)
    full = torch.cat([uncropped_measurements(batches, k, a, b) for a, b in batches.ranges()])
    on_grid = solve_full(gram, rhs_spectra_full(batches, full))
    recovered = extract_kernel(on_grid, (32, 32)).numpy()
    assert np.abs(recovered - truth).max() < 1e-8 * np.abs(truth).max()
    # and nothing outside the kernel window (the truth is non-negative)
    assert float(on_grid.abs().sum()) == pytest.approx(float(truth.sum()), rel=1e-8)


@pytest.mark.parametrize("convention", ["source", "sensor"])
def test_streaming_normal_operator_is_the_whole_one(scenes: np.ndarray,
                                                    convention: str) -> None:
    """Batches, scales and the cache do not change ``Σ s_i² B_iᵀB_i`` (against one operator
    over all pairs, scenes scaled)."""
    rng = np.random.default_rng(0)
    k = torch.as_tensor(rng.standard_normal((3, 3, 32, 32)))
    s = torch.as_tensor(rng.uniform(0.5, 1.5, len(scenes)))
    whole = KernelSpaceOperator(torch.as_tensor(scenes) * s[:, None, None, None], "paper",
                                convention, (32, 32))
    expected = whole.adjoint(whole.forward(k))
    per_pair = PairBatches(scenes, "paper", convention, (32, 32))._per_pair
    n = len(scenes)
    # none, some batches (the first two of 6 pairs: a budget of 13 pairs), all
    for cache, kept in ((0, 0), (13 * per_pair, min(12, n)), (2**30, n)):
        batches = PairBatches(scenes, "paper", convention, (32, 32), batch_size=6,
                              cache_bytes=cache)
        batches.scales = s
        for _ in range(2):                          # the second pass uses the kept operators
            got = batches.normal(k)
            assert float((got - expected).abs().max()) <= 1e-10 * float(expected.abs().max())
        # pairs whose operators are kept between passes (at most cache_bytes of them)
        assert batches._cached_pairs == kept, (cache, batches._cached_pairs)
    # the right-hand side and the forward model, with the kernels' spectra shared by the
    # batches and the adjoint spectra summed before one inverse FFT
    y = torch.as_tensor(rng.standard_normal((n, 3, *scenes.shape[-2:])))
    expected_rhs = whole.adjoint(y)
    assert float((batches.rhs(y) - expected_rhs).abs().max()) <= \
        1e-10 * float(expected_rhs.abs().max())
    predicted = torch.cat([p * s[:, None, None, None]
                           for _a, _b, _op, s, p in batches.predictions(k)])
    expected_y = whole.forward(k)
    assert float((predicted - expected_y).abs().max()) <= 1e-10 * float(expected_y.abs().max())


@pytest.mark.parametrize("convention", ["source", "sensor"])
def test_solver_converges_to_the_exact_kernels(scenes: np.ndarray, convention: str) -> None:
    truth = known_eigen_kernels()
    model = KernelModel(kernels=truth.astype(np.float32), basis="paper", convention=convention,
                        sensor_shape=(32, 32), channels=("R", "G", "B"))
    y = predict(model, scenes.astype(np.float32), dtype=torch.float64)
    batches = PairBatches(scenes, "paper", convention, (32, 32), batch_size=8)
    kernels, info, _ = solve_kernels(batches, y, tolerance=1e-9, max_iterations=1000)
    assert info.converged and info.relative_residual < 1e-8
    assert _metrics(kernels.numpy(), model.kernels.astype(np.float64))["error"] < 1e-4
    # the Gram preconditioner: far fewer iterations than the scale alone would need
    assert info.iterations < 300


@pytest.mark.parametrize("convention", ["source", "sensor"])
def test_fit_pairs_defaults_recover_eigen_kernel_pairs(scenes: np.ndarray,
                                                       convention: str) -> None:
    """Issue 23 item 5: noise-free pairs of the eigen-kernel model itself. fit-pairs' defaults
    (per-pair scales, non-negative kernels, no ridge, no difference prior) give its kernels
    back; the earlier defaults' priors (``--tikhonov 1e-2 --difference 1``) do not, even
    solved to convergence: they were the bias (plus the early-stopped CG)."""
    truth = known_eigen_kernels()
    model = KernelModel(kernels=truth.astype(np.float32), basis="paper", convention=convention,
                        sensor_shape=(32, 32), channels=("R", "G", "B"))
    truth = model.kernels.astype(np.float64)
    y = predict(model, scenes.astype(np.float32), dtype=torch.float64)
    fit = fit_pairs(scenes, y, PairFitOptions(basis="paper", convention=convention))
    m = _metrics(fit.kernels, truth)
    assert m["base"] >= 0.999 and m["v"] >= 0.99 and m["h"] >= 0.99, m
    assert fit.training_error.max() < 1e-3
    assert np.allclose(fit.scales, 1.0, atol=1e-3)
    start, newton = fit.history[-2:]
    assert start["stage"] == "start" and start["relative_residual"] < START_TOLERANCE
    assert newton["converged"]                                  # the non-negative solve
    old = fit_pairs(scenes, y, PairFitOptions(basis="paper", convention=convention,
                                              tikhonov=1e-2, difference=1.0))
    m_old = _metrics(old.kernels, truth)
    assert min(m_old["v"], m_old["h"]) < 0.95, m_old
    assert m_old["error"] > 3 * m["error"]


def _dense_nnls_problem(seed: int = 0):
    """A dense, ill-conditioned least squares ``min ‖A K − y‖`` over ``K ≥ 0`` per channel, in
    the solver's layout ``(K, C, H, W)`` = (2, 2, 4, 5): 40 unknowns per channel, 60 rows."""
    rng = np.random.default_rng(seed)
    shape = (2, 2, 4, 5)
    n = 2 * 4 * 5
    mats = [rng.standard_normal((60, n)) @ np.diag(np.logspace(0, -3, n)) for _ in range(2)]
    truth = np.abs(rng.standard_normal(shape)) * (rng.random(shape) < 0.5)
    ys = [mats[c] @ truth[:, c].ravel() + 1e-3 * rng.standard_normal(60) for c in range(2)]

    def normal(k: torch.Tensor) -> torch.Tensor:
        out = torch.empty_like(k)
        for c in range(2):
            a = torch.as_tensor(mats[c], dtype=k.dtype)
            out[:, c] = (a.T @ (a @ k[:, c].reshape(-1))).reshape(k[:, c].shape)
        return out

    rhs = torch.stack([torch.as_tensor(mats[c].T @ ys[c]).reshape(2, 4, 5) for c in range(2)],
                      dim=1)
    return mats, ys, normal, rhs


@pytest.mark.parametrize("hessian_dtype", [torch.float64, torch.float32])
def test_projected_newton_is_scipys_nnls(hessian_dtype: torch.dtype) -> None:
    """The non-negative least squares of a dense ill-conditioned problem (singular values
    over 3 decades) against scipy's active-set NNLS (Lawson–Hanson, an independent method),
    with the Newton step's CG on exact or on float32 products."""
    from scipy.optimize import nnls

    mats, ys, normal, rhs = _dense_nnls_problem()

    def hessian(v: torch.Tensor) -> torch.Tensor:
        return normal(v.to(hessian_dtype)).to(v.dtype)

    start = torch.zeros_like(rhs)
    x, info = projected_newton(normal, rhs, start, iterations=200, cg_iterations=40,
                               tolerance=1e-11, hessian=hessian)
    assert info["converged"] and info["kkt_residual"] < 1e-11 and not info["stalled"]
    for c in range(2):
        expected, _ = nnls(mats[c], ys[c], maxiter=10_000)
        got = x[:, c].reshape(-1).numpy()
        assert np.array_equal(got == 0, expected == 0)         # the same active set
        assert np.abs(got - expected).max() < 1e-5 * np.abs(expected).max()
        assert (expected == 0).sum() > 5              # the constraint binds
    assert float(kkt_residual(normal, rhs, x).max()) < 1e-11


def test_the_line_search_backtracks_on_cheap_products_and_ends_on_exact_ones() -> None:
    """A step 30× too long backtracks: with float32 trial products it takes the same step
    sizes as with exact ones and returns the exact ``N x⁺``; with the wrong products (``−N``)
    it never takes a step that does not decrease the objective exactly."""
    _mats, _ys, normal, rhs = _dense_nnls_problem(2)
    x = torch.rand(rhs.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    nx = normal(x)
    g = nx - rhs
    d = -30 * g / float(g.abs().max())

    def project(v: torch.Tensor) -> torch.Tensor:
        return v.clamp_min(0)

    def objective(k: torch.Tensor) -> torch.Tensor:
        return (0.5 * k * normal(k) - rhs * k).sum(dim=(0, 2, 3))

    exact = _armijo_step(normal, normal, project, x, nx, g, d)
    cheap = _armijo_step(normal, lambda v: normal(v.float()).to(v.dtype), project, x, nx, g, d)
    assert bool(exact[2].all()) and bool(cheap[2].all())
    assert not torch.equal(exact[0], x + d)                  # it did backtrack
    assert torch.allclose(cheap[0], exact[0], rtol=0, atol=1e-12)
    assert torch.equal(cheap[1], normal(cheap[0]))           # the exact product at x⁺
    assert bool((objective(exact[0]) < objective(x)).all())
    wrong = _armijo_step(normal, lambda v: -normal(v), project, x, nx, g, d)
    moved = wrong[2]
    assert not bool(moved.all())                 # the exact check turned a trial down
    assert torch.equal(wrong[0][:, ~moved], x[:, ~moved])
    assert bool((objective(wrong[0]) <= objective(x)).all())
    assert torch.equal(wrong[1], normal(wrong[0]))


def test_kkt_residual_does_not_depend_on_units() -> None:
    """Scaling the data (``rhs``) or the operator leaves the relative natural residual of the
    same (rescaled) point unchanged, and it vanishes only at the minimiser."""
    _mats, _ys, normal, rhs = _dense_nnls_problem(1)
    x, _ = projected_newton(normal, rhs, torch.zeros_like(rhs), iterations=200,
                            cg_iterations=40, tolerance=1e-13)
    noise = torch.rand(x.shape, generator=torch.Generator().manual_seed(0), dtype=x.dtype)
    point = x + 0.01 * x.abs().max() * noise
    base = kkt_residual(normal, rhs, point)
    assert float(kkt_residual(normal, rhs, x).max()) < 1e-12 < float(base.min())
    scaled_data = kkt_residual(normal, 1e6 * rhs, 1e6 * point)
    scaled_operator = kkt_residual(lambda v: 1e6 * normal(v), 1e6 * rhs, point)
    assert torch.allclose(scaled_data, base, rtol=1e-2)
    assert torch.allclose(scaled_operator, base, rtol=1e-2)


def test_projected_newton_leaves_too_coarse_cheap_products_for_exact_ones() -> None:
    """Cheap products so wrong that their steps never improve (``−N``: its Newton step points
    uphill): the solver leaves them once ``STALL_STEPS`` steps bring no new low (or no step
    size descends), goes on with the exact products and reaches the tolerance, on any
    machine."""
    _mats, _ys, normal, rhs = _dense_nnls_problem(0)
    x, info = projected_newton(normal, rhs, torch.zeros_like(rhs), iterations=300,
                               cg_iterations=40, tolerance=1e-11,
                               hessian=lambda v: -normal(v))
    assert 1 <= info["exact_hessian_from"] <= STALL_STEPS
    assert info["converged"] and not info["stalled"]
    assert float(x.min()) >= 0 and float(kkt_residual(normal, rhs, x).max()) < 1e-11


def test_a_stall_leaves_the_cheap_products_only_when_they_are_less_precise_than_asked() -> None:
    """The stall check compares the cheap products' error on the last Newton step with the
    CG's forcing term: float32 products (relative error ~1e-7) pass at a forcing of 1e-3, so
    a stalled residual is the active set's swing and they are kept; bfloat16 ones (8-bit
    mantissa, ~4e-3), the wrong operator (``−N``) or no step at all are too coarse."""
    _mats, _ys, normal, _rhs = _dense_nnls_problem(0)
    step = torch.as_tensor(np.random.default_rng(1).random((2, 2, 4, 5)))

    def in_precision(dtype: torch.dtype):
        return lambda v: normal(v.to(dtype).to(torch.float64))

    assert not _cheap_products_too_coarse(normal, in_precision(torch.float32), step, 1e-3)
    assert _cheap_products_too_coarse(normal, in_precision(torch.bfloat16), step, 1e-3)
    assert _cheap_products_too_coarse(normal, lambda v: -normal(v), step, 1e-3)
    assert _cheap_products_too_coarse(normal, normal, torch.zeros_like(step), 1e-3)


def test_projected_newton_with_coarse_products_ends_at_the_tolerance() -> None:
    """bfloat16 products (8-bit mantissa) on a problem with κ(N) ≈ 10⁶, no preconditioner.
    Where they stop improving depends on the machine's rounding (one machine: near 4e-7,
    then the exact products took over; an AVX512-BF16 one: they crawled to 3.7e-11 in 255
    steps first); either way the solve ends converged, at the exact products' tolerance."""
    _mats, _ys, normal, rhs = _dense_nnls_problem(0)

    def coarse(v: torch.Tensor) -> torch.Tensor:
        return normal(v.to(torch.bfloat16).to(torch.float32)).to(v.dtype)

    x, info = projected_newton(normal, rhs, torch.zeros_like(rhs), iterations=400,
                               cg_iterations=40, tolerance=1e-11, hessian=coarse)
    assert info["converged"] and not info["stalled"]
    if info["exact_hessian_from"] is not None:   # the cheap stage alone did not get there
        assert min(info["history"][: info["exact_hessian_from"] + 1]) > 1e-11
    assert float(x.min()) >= 0 and float(kkt_residual(normal, rhs, x).max()) < 1e-11


def test_batch_size_keeps_a_batch_under_the_reuse_threshold() -> None:
    """On the CPU a batch's spectra stay under ``BATCH_BYTES`` (glibc reuses such blocks,
    :mod:`psfkit.cli.allocator`); small pairs keep ``DEFAULT_BATCH``; other devices too."""
    per_pair = 3 * 3 * 192 * 97 * 16                  # source side, 128² float64: 2.7 MB
    assert auto_batch_size(per_pair) == BATCH_BYTES // per_pair == 9
    assert auto_batch_size(10) == DEFAULT_BATCH
    assert auto_batch_size(10 * BATCH_BYTES) == 1
    assert auto_batch_size(per_pair, "cuda:0") == DEFAULT_BATCH
    b = PairBatches(bench_scenes(3, (128, 128)), "paper", "source", (128, 128))
    assert b.batch_size == 9


def test_float32_twin_is_the_same_operator(scenes: np.ndarray) -> None:
    """``astype(float32)`` keeps pairs, scales and regularisation: its normal operator agrees
    with the float64 one to float32 rounding."""
    rng = np.random.default_rng(3)
    batches = PairBatches(scenes, "paper", "source", (32, 32), batch_size=6)
    batches.scales = torch.as_tensor(rng.uniform(0.5, 1.5, len(scenes)))
    k = torch.as_tensor(rng.standard_normal((3, 3, 32, 32)))
    exact = regularised_normal(batches, 2.0, 3.0)(k)
    twin = regularised_normal(batches.astype(torch.float32), 2.0, 3.0)(k)
    assert twin.dtype == torch.float64
    assert float((twin - exact).abs().max()) < 1e-5 * float(exact.abs().max())


@pytest.mark.parametrize("coupled", [True, False])
def test_preconditioner_in_float32_is_the_float64_one(scenes: np.ndarray,
                                                      coupled: bool) -> None:
    """``dtype=float32`` (the Newton steps' preconditioner) applies the same ``P`` to a float64
    residual, to float32 rounding, and hands it back in float64."""
    rng = np.random.default_rng(4)
    gram = PairBatches(scenes, "paper", "source", (32, 32), batch_size=6).gram()
    r = torch.as_tensor(rng.standard_normal((3, 3, 32, 32)))
    exact = gram.preconditioner(0.1, 1.0, coupled=coupled)(r)
    cheap = gram.preconditioner(0.1, 1.0, coupled=coupled, dtype=torch.float32)(r)
    assert exact.dtype == cheap.dtype == torch.float64
    error = float((cheap - exact).abs().max()) / float(exact.abs().max())
    assert 0 < error < 1e-5, error                    # computed in float32, not float64
