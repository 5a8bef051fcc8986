"""Forward operators of ekdun: exact adjoints, agreement with spatial convolution, FFT counts."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal
import torch

from ekdun.errors import ConfigurationError, KernelShapeError, TensorShapeError
from ekdun.physics import (
    EigenKernelOperator,
    MultiPSFOperator,
    ShiftInvariantOperator,
)
from psfkit import forward as Fn
from psfkit.errors import InvalidInputError
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.forward.weights import get_basis

KINDS = ("si", "ek-sensor", "ek-source", "multi")
TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


@pytest.fixture(autouse=True)
def _one_intra_op_thread(torch_one_thread):
    """Tiny tensors: every test here runs with one torch thread (shared fixture)."""


def make_operator(kind: str, sensor: tuple[int, int], colours: int, dtype: torch.dtype,
                  kernel_shape: tuple[int, int] | None = None, trainable: bool = False,
                  basis: str = "paper", seed: int = 0):
    """A random operator of ``kind``; kernels are non-negative like PSFs."""
    gen = torch.Generator().manual_seed(seed)
    hk, wk = kernel_shape or sensor
    if kind == "si":
        return ShiftInvariantOperator(torch.rand(colours, hk, wk, generator=gen, dtype=dtype),
                                      sensor, trainable=trainable)
    if kind.startswith("ek"):
        n = get_basis(basis).n_kernels
        kernels = torch.rand(n, colours, hk, wk, generator=gen, dtype=dtype)
        return EigenKernelOperator.from_basis(kernels, basis, sensor,
                                              convention=kind.split("-")[1],
                                              trainable=trainable)
    if kind == "multi":
        psfs = torch.rand(2, colours, hk, wk, generator=gen, dtype=dtype)
        return MultiPSFOperator(psfs, sensor, trainable=trainable)
    raise AssertionError(kind)


def inner(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() * b.double()).sum())


SHAPES = [  # (batch, colours, H', W', kernel shape)
    (1, 1, 8, 12, None),
    (2, 3, 9, 13, (5, 6)),   # odd sensor, even/odd kernel smaller than the sensor
    (2, 1, 10, 7, (10, 7)),
    (1, 3, 6, 6, (3, 4)),
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s[:4])))
@pytest.mark.parametrize("kind", KINDS)
def test_dot_product_adjoint(kind, shape, dtype):
    batch, colours, h, w, kshape = shape
    op = make_operator(kind, (h, w), colours, dtype, kshape)
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(batch, op.channels, h, w, generator=gen, dtype=dtype)
    y = torch.rand(batch, op.channels, h, w, generator=gen, dtype=dtype)
    ax, aty = op.A(x), op.A_adjoint(y)
    assert ax.shape == x.shape and aty.shape == y.shape
    assert ax.dtype == aty.dtype == dtype
    lhs, rhs = inner(ax, y), inner(x, aty)
    assert abs(lhs - rhs) / abs(lhs) <= TOL[dtype]


@pytest.mark.parametrize("kind", KINDS)
def test_adjoint_is_the_transpose_of_the_dense_matrix(kind):
    """Build A column by column on a tiny grid and compare Aᵀ with the matrix transpose."""
    op = make_operator(kind, (5, 6), 1, torch.float64, (3, 4), seed=3)
    n = op.channels * 5 * 6
    eye = torch.eye(n, dtype=torch.float64).reshape(n, op.channels, 5, 6)
    a = op.A(eye).reshape(n, n).T           # column j = A e_j
    at = op.A_adjoint(eye).reshape(n, n).T
    torch.testing.assert_close(at, a.T, rtol=0, atol=1e-13)
    assert a.abs().sum() > 0


def _direct(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Linear convolution of x (H, W) with a centred kernel, cropped to x's size."""
    hk, wk = kernel.shape
    full = scipy.signal.convolve2d(x, kernel, mode="full")
    return full[hk // 2:hk // 2 + x.shape[0], wk // 2:wk // 2 + x.shape[1]]


@pytest.mark.parametrize("sensor,kshape,padding", [
    ((8, 12), (8, 12), 2), ((9, 7), (4, 5), 2), ((7, 10), (7, 9), 3), ((6, 5), (1, 1), 2)])
def test_shift_invariant_equals_direct_spatial_convolution(sensor, kshape, padding):
    gen = torch.Generator().manual_seed(4)
    psf = torch.randn(3, *kshape, generator=gen, dtype=torch.float64)
    op = ShiftInvariantOperator(psf, sensor, scene_padding=padding)
    x = torch.randn(2, 3, *sensor, generator=gen, dtype=torch.float64)
    y = op.A(x)
    for b in range(2):
        for c in range(3):
            np.testing.assert_allclose(y[b, c].numpy(), _direct(x[b, c].numpy(),
                                                                psf[c].numpy()), atol=1e-12)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_eigen_kernel_equals_direct_weighted_convolutions(convention):
    sensor = (9, 10)
    op = make_operator(f"ek-{convention}", sensor, 3, torch.float64, (5, 8), seed=5)
    x = torch.rand(1, 3, *sensor, dtype=torch.float64, generator=torch.Generator()
                   .manual_seed(6))
    weights = op.weights.numpy()
    expected = np.zeros((3, *sensor))
    for k in range(3):
        for c in range(3):
            kernel = op.kernels[k, c].numpy()
            if convention == "sensor":
                expected[c] += weights[k] * _direct(x[0, c].numpy(), kernel)
            else:
                expected[c] += _direct(weights[k] * x[0, c].numpy(), kernel)
    np.testing.assert_allclose(op.A(x)[0].numpy(), expected, atol=1e-12)
    # Eq. 7 weights: base 1 − Wh − Wv, then Wv, Wh
    np.testing.assert_allclose(weights, get_basis("paper").maps(sensor))


def test_multi_psf_convolves_each_channel_with_its_own_psf():
    op = make_operator("multi", (6, 8), 3, torch.float64, (3, 5), seed=7)
    x = torch.rand(1, 6, 6, 8, dtype=torch.float64)
    y = op.A(x)
    for n in range(2):
        for c in range(3):
            np.testing.assert_allclose(
                y[0, 3 * n + c].numpy(),
                _direct(x[0, 3 * n + c].numpy(), op.psfs[n, c].numpy()), atol=1e-12)
    tiled = op.tile(torch.ones(2, 3, 6, 8))
    assert tiled.shape == (2, 6, 6, 8)


@pytest.mark.parametrize("sensor", [(8, 12), (9, 11), (7, 6)])
def test_point_source_at_scene_centre_images_to_the_kernel(sensor):
    h, w = sensor
    psf = torch.rand(3, h, w, dtype=torch.float64)
    op = ShiftInvariantOperator(psf)
    x = torch.zeros(1, 3, h, w, dtype=torch.float64)
    x[..., h // 2, w // 2] = 1.0
    torch.testing.assert_close(op.A(x)[0], psf, rtol=0, atol=1e-14)


def test_pad_and_crop_are_adjoint_and_centred():
    x = torch.rand(2, 3, 5, 7, dtype=torch.float64)
    z = Fn.pad(x, (10, 14))
    assert z.shape == (2, 3, 10, 14)
    torch.testing.assert_close(z[..., 2:7, 3:10], x)        # (10−5)//2, (14−7)//2
    assert z.sum() == pytest.approx(x.sum().item())
    u = torch.rand(2, 3, 10, 14, dtype=torch.float64)
    assert inner(Fn.pad(x, (10, 14)), u) == pytest.approx(inner(x, Fn.crop(u, (5, 7))),
                                                            rel=1e-14)
    assert Fn.padded_shape((4, 6), 2) == (8, 12) and Fn.centre_offset((4, 6), (8, 12)) == (2, 3)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_eigen_kernel_with_equal_kernels_equals_shift_invariant(convention):
    psf = torch.rand(3, 6, 7, dtype=torch.float64)
    si = ShiftInvariantOperator(psf, (8, 9))
    ek = EigenKernelOperator.from_basis(psf.repeat(3, 1, 1, 1), "paper", (8, 9),
                                       convention=convention)
    assert ek.n_kernels == 3
    x = torch.rand(2, 3, 8, 9, dtype=torch.float64)
    torch.testing.assert_close(ek.A(x), si.A(x), rtol=0, atol=1e-13)
    torch.testing.assert_close(ek.A_adjoint(x), si.A_adjoint(x), rtol=0, atol=1e-13)
    # while different kernels give a different model
    ek.kernels[1] *= 2.0
    ek.refresh_spectra()
    assert (ek.A(x) - si.A(x)).abs().max() > 1e-3


def test_cropped_inverse_fft_equals_full_inverse_then_crop():
    spectrum = torch.fft.rfft2(torch.rand(2, 3, 10, 13, dtype=torch.float64))
    full = torch.fft.irfft2(spectrum, s=(10, 13))
    torch.testing.assert_close(Fn.irfft2(spectrum, (10, 13), (5, 6)), full[..., :5, :6])
    torch.testing.assert_close(Fn.irfft2(spectrum, (10, 13)), full)


@pytest.mark.parametrize("kind,basis,forward,adjoint", [
    ("si", "si", (1, 1), (1, 1)),
    ("ek-sensor", "paper", (1, 3), (3, 1)),
    ("ek-source", "paper", (3, 1), (1, 3)),
    ("ek-sensor", "paper+odd", (1, 5), (5, 1)),
    ("multi", "si", (1, 1), (1, 1)),
])
def test_fft_counts(fft_counter, kind, basis, forward, adjoint):
    op = make_operator(kind, (8, 10), 3, torch.float32, basis=basis, trainable=True)
    counter = fft_counter
    counter.take()
    prepared = op.prepare()   # all kernel FFTs in one batched call, once per forward pass
    assert counter.take() == (1, 0)
    x = torch.rand(2, op.channels, 8, 10)
    prepared.A(x)
    assert counter.take() == forward
    prepared.A_adjoint(x)
    assert counter.take() == adjoint
    # fixed kernels: spectra are cached, so the module's A takes no kernel FFT either
    op.kernels.requires_grad_(False)
    op.refresh_spectra()
    counter.take()
    op.A(x)
    assert counter.take() == forward
    op.A_adjoint(x)
    assert counter.take() == adjoint


def test_cached_spectra_follow_dtype_and_load_state_dict():
    op = make_operator("ek-sensor", (6, 8), 3, torch.float32)
    x = torch.rand(1, 3, 6, 8, dtype=torch.float64)
    with pytest.raises(TensorShapeError,
                       match=r"is torch\.float64 but the operator is torch\.float32"):
        op.A(x)
    op64 = op.to(torch.float64)       # recomputed in complex128, imaginary parts kept
    assert op64.spectra().dtype == torch.complex128
    torch.testing.assert_close(op64.spectra(), Fn.kernel_spectra(op64.kernels, op.grid_shape))
    assert op64.spectra().imag.abs().max() > 0
    other = make_operator("ek-sensor", (6, 8), 3, torch.float64, seed=9)
    op64.load_state_dict(other.state_dict())
    torch.testing.assert_close(op64.A(x), other.A(x))
    assert "_spectra_cache" not in op64.state_dict()


@pytest.mark.parametrize("kind", KINDS)
def test_gradcheck_wrt_scene_and_trainable_kernels(kind):
    op = make_operator(kind, (5, 6), 1, torch.float64, (3, 4), trainable=True, seed=2)
    x = torch.rand(1, op.channels, 5, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: op.A(t), (x,))
    assert torch.autograd.gradcheck(lambda t: op.A_adjoint(t), (x,))
    kernels = op.kernels.detach().clone().requires_grad_(True)
    weights = op.weights

    def through_kernels(k: torch.Tensor) -> torch.Tensor:
        spectra = Fn.kernel_spectra(k, op.grid_shape)
        return (Fn.eigen_kernel_forward(x.detach(), spectra, weights, op.grid_shape,
                                        op.convention)
                + Fn.eigen_kernel_adjoint(x.detach(), spectra.conj(), weights,
                                          op.grid_shape, op.convention))

    assert torch.autograd.gradcheck(through_kernels, (kernels,))
    # the module's kernels are a Parameter that receives gradients
    op.A(x.detach()).sum().backward()
    assert op.kernels.grad is not None and op.kernels.grad.abs().sum() > 0


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_kernel_file_round_trip(tmp_path, convention):
    rng = np.random.default_rng(0)
    kernels = rng.random((5, 3, 6, 7)).astype(np.float32)
    model = KernelModel(kernels=kernels, basis="paper+odd", convention=convention,
                        sensor_shape=(8, 9), optical_center=(3.0, 5.0))
    back = load_kernels(save_kernels(tmp_path / "k.npz", model))
    op = EigenKernelOperator.from_kernel_model(back, trainable=True)
    assert op.kernel_names == ("base", "v", "h", "v_odd", "h_odd")
    assert op.convention == convention and op.sensor_shape == (8, 9) and op.trainable
    assert isinstance(op.kernels, torch.nn.Parameter)
    np.testing.assert_array_equal(op.kernels.detach().numpy(), kernels)
    np.testing.assert_allclose(op.weights.numpy(), model.weight_maps(), rtol=1e-6)
    direct = EigenKernelOperator.from_basis(kernels, "paper+odd", (8, 9),
                                            optical_center=(3.0, 5.0), convention=convention)
    x = torch.rand(1, 3, 8, 9)
    torch.testing.assert_close(op.A(x), direct.A(x))
    si = KernelModel.shift_invariant(kernels[0], sensor_shape=(8, 9))
    op_si = EigenKernelOperator.from_kernel_model(load_kernels(save_kernels(tmp_path / "s.npz",
                                                                            si)))
    torch.testing.assert_close(op_si.A(x), ShiftInvariantOperator.from_psf(kernels[0],
                                                                           (8, 9)).A(x))



@pytest.mark.parametrize("basis,convention", [("si", "sensor"), ("paper", "sensor"),
                                              ("paper", "source")])
def test_every_command_builds_the_same_operator_from_a_kernel_file(basis, convention):
    """The data contract: fit-pairs' predictions, the networks' physics (trainable or not) and
    the classical solvers' operators are the one operator of psfkit.forward.operator, bit for
    bit (same FFTs in the same order); the padded-scene form agrees to rounding."""
    from ekdun.reconstruction.classical import ModelReconstructor
    from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
    from psfkit.fitting.pairs.fit import predict
    from psfkit.forward.operator import SpectralOperator

    rng = np.random.default_rng(2)
    n = 1 if basis == "si" else 3
    model = KernelModel(kernels=rng.random((n, 3, 6, 7)).astype(np.float32), basis=basis,
                        convention=convention, sensor_shape=(8, 9), optical_center=(3.0, 5.0))
    x = rng.random((2, 3, 8, 9)).astype(np.float32)
    xt = torch.as_tensor(x)
    one = SpectralOperator.from_kernel_model(model).A(xt)
    with torch.no_grad():
        outputs = {
            "predict": torch.as_tensor(predict(model, x)),
            "ekdun operator": EigenKernelOperator.from_kernel_model(model).A(xt),
            "network physics": EigenKernelOperator.from_kernel_model(model, trainable=True).A(xt),
        }
    for name, y in outputs.items():
        assert torch.equal(y, one), name
    f64 = SpectralOperator.from_kernel_model(model, torch.float64)
    padded = ExtendedSceneOperator.from_kernel_model(model, torch.float64)
    x64 = xt.double()
    torch.testing.assert_close(padded.A(padded.pad(x64)), f64.A(x64), rtol=0, atol=1e-12)
    solver = ModelReconstructor(model).solver_operator
    assert isinstance(solver, ExtendedSceneOperator)
    torch.testing.assert_close(solver.A(solver.pad(xt)), one, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kind", KINDS)
def test_every_ekdun_operator_passes_the_base_class_tests(kind):
    """psfkit.forward.base.LinearOperator: adjointness test, and norm() against the dense
    matrix's largest singular value."""
    op = make_operator(kind, (5, 6), 1, torch.float64, (3, 4), seed=3)
    assert op.adjointness_error() < 1e-14
    assert make_operator(kind, (9, 13), 3, torch.float32, (5, 6)).adjointness_error() < 1e-6
    n = op.channels * 5 * 6
    dense = op.A(torch.eye(n, dtype=torch.float64).reshape(n, op.channels, 5, 6))
    sigma = np.linalg.svd(dense.reshape(n, n).numpy(), compute_uv=False)[0]
    assert op.norm(tol=1e-8, max_iterations=5000) == pytest.approx(sigma, rel=1e-6)
    assert op.prepare().norm(tol=1e-8, max_iterations=5000) == pytest.approx(sigma, rel=1e-6)

def test_bad_inputs_raise_one_line_errors():
    op = make_operator("ek-sensor", (8, 10), 3, torch.float32)
    with pytest.raises(TensorShapeError, match="measurement is 8x11 but the operator's sensor "
                                               "is 8x10"):
        op.A_adjoint(torch.zeros(1, 3, 8, 11))
    with pytest.raises(TensorShapeError, match="scene has 1 channel\\(s\\) but the operator "
                                               "has 3"):
        op.A(torch.zeros(1, 1, 8, 10))
    with pytest.raises(TensorShapeError, match="must be \\(B, C, H, W\\)"):
        op.A(torch.zeros(3, 8, 10))
    with pytest.raises(KernelShapeError, match="kernels 9x10 are larger than the sensor 8x10"):
        ShiftInvariantOperator(torch.zeros(3, 9, 10), (8, 10))
    with pytest.raises(KernelShapeError, match="weight maps must be"):
        EigenKernelOperator(torch.zeros(3, 3, 4, 4), torch.zeros(2, 8, 10))
    with pytest.raises(ConfigurationError, match="scene_padding must be an integer >= 2"):
        ShiftInvariantOperator(torch.zeros(3, 4, 4), (8, 10), scene_padding=1)
    with pytest.raises(ConfigurationError, match="convention must be"):
        EigenKernelOperator.from_basis(torch.zeros(3, 3, 4, 4), convention="lens")
    with pytest.raises(KernelShapeError, match="NaN/Inf"):
        ShiftInvariantOperator(torch.full((1, 4, 4), float("nan")))
    # all are psfkit errors, so the CLIs print them as one line
    assert issubclass(TensorShapeError, InvalidInputError)
    for exc in (TensorShapeError("a"), KernelShapeError("b")):
        assert "\n" not in str(exc)


@pytest.mark.parametrize("kind", KINDS)
def test_buffer_reusing_path_equals_the_autograd_path(kind):
    """Outside autograd the kernels reuse buffers in place; results must not change."""
    op = make_operator(kind, (9, 12), 3, torch.float64, (5, 7), seed=8)
    x = torch.rand(2, op.channels, 9, 12, dtype=torch.float64)
    with torch.no_grad():
        forward, adjoint = op.A(x), op.A_adjoint(x)
    tracked = x.clone().requires_grad_(True)
    torch.testing.assert_close(op.A(tracked).detach(), forward, rtol=0, atol=1e-13)
    torch.testing.assert_close(op.A_adjoint(tracked).detach(), adjoint, rtol=0, atol=1e-13)
    assert op.A(tracked).requires_grad
