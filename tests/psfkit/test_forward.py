"""The one forward model (psfkit.forward): torch-free geometry, the shared FFT counter."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from psfkit.forward import (
    KernelSpaceOperator,
    centre_offset,
    count_ffts,
    eigen_kernel_forward,
    kernel_spectra,
    largest_eigenvalue,
    operator_norm,
    pad,
    padded_scene_adjoint,
    padded_scene_forward,
    padded_shape,
    rfft2,
)
from tests.helpers.operators import extract_kernel


def test_geometry_and_kernel_file_load_without_torch():
    code = ("import sys, psfkit.forward, psfkit.forward.kernelfile; "
            "assert psfkit.forward.padded_shape((3, 5), 2) == (6, 10); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"
    assert padded_shape((4, 6), 3) == (12, 18)


def test_count_ffts_counts_every_user_and_nests():
    x = torch.rand(2, 1, 6, 7, dtype=torch.float64)
    with count_ffts() as outer:
        rfft2(x)
        with count_ffts() as inner:
            kernel_spectra(torch.rand(1, 1, 3, 3, dtype=torch.float64), (12, 14))
            # the kernel-space form of fit-pairs: scene spectra once, then 1 + 1 per forward
            op = KernelSpaceOperator(x, "si", "sensor", (6, 7))
            assert inner.take() == (2, 0)
            op.forward(torch.rand(1, 1, 6, 7, dtype=torch.float64))
            assert inner.take() == (1, 1)
    assert outer.as_tuple() == (4, 1)
    rfft2(x)                               # outside every block: not counted
    assert outer.as_tuple() == (4, 1)


# --- Eq. 7 with the scene on the padded grid ------------------------------------------------

SENSOR, GRID = (4, 5), (8, 10)


def _dense_reference(x, kernels, weights, convention):
    """Eq. 7 from its definition, one output pixel at a time (numpy loops, no FFT): the scene
    on the whole grid, the view its centred block, kernel origins at their centre pixels."""
    top, left = (GRID[0] - SENSOR[0]) // 2, (GRID[1] - SENSOR[1]) // 2
    n_k, channels, hk, wk = kernels.shape
    out = np.zeros((x.shape[0], channels, *SENSOR))
    for k in range(n_k):
        for i in range(SENSOR[0]):
            for j in range(SENSOR[1]):
                for a in range(hk):
                    for b in range(wk):
                        # y[i, j] gets K[a, b]·x at the grid pixel displaced by (a, b) − origin
                        p = (top + i - (a - hk // 2)) % GRID[0]
                        q = (left + j - (b - wk // 2)) % GRID[1]
                        if convention == "source":
                            value = weights[k, p, q] * x[:, :, p, q]
                            out[:, :, i, j] += kernels[k, :, a, b] * value
                        else:
                            out[:, :, i, j] += (weights[k, i, j] * kernels[k, :, a, b]
                                                * x[:, :, p, q])
    return out


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_padded_scene_forward_is_eq7_and_its_adjoint_is_exact(convention):
    rng = np.random.default_rng(5)
    kernels = rng.standard_normal((3, 2, 3, 4))
    shape = SENSOR if convention == "sensor" else GRID
    weights = rng.random((3, *shape))
    x = rng.standard_normal((2, 2, *GRID))
    y = rng.standard_normal((2, 2, *SENSOR))
    spectra = kernel_spectra(torch.as_tensor(kernels), GRID)
    w = torch.as_tensor(weights)
    forward = padded_scene_forward(torch.as_tensor(x), spectra, w, SENSOR, convention)
    np.testing.assert_allclose(forward.numpy(), _dense_reference(x, kernels, weights, convention),
                               rtol=0, atol=1e-12)
    adjoint = padded_scene_adjoint(torch.as_tensor(y), spectra.conj().resolve_conj(), w, GRID,
                                   convention)
    assert adjoint.shape == (2, 2, *GRID)
    lhs, rhs = float((forward.numpy() * y).sum()), float((x * adjoint.numpy()).sum())
    assert abs(lhs - rhs) < 1e-12 * max(abs(lhs), 1.0)
    # one kernel with no weights: the shift-invariant model in either convention
    si = padded_scene_forward(torch.as_tensor(x), spectra[:1], None, SENSOR, convention)
    np.testing.assert_allclose(si.numpy(), _dense_reference(x, kernels[:1], np.ones((1, *shape)),
                                                            convention), rtol=0, atol=1e-12)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_padded_scene_model_of_a_scene_inside_the_view_is_the_sensor_sized_model(convention):
    rng = np.random.default_rng(6)
    kernels = torch.as_tensor(rng.standard_normal((3, 1, 3, 5)))
    sensor_weights = torch.as_tensor(rng.random((3, *SENSOR)))
    # source side: scene weights that are the sensor-sized ones in the view, anything outside
    grid_weights = torch.as_tensor(rng.random((3, *GRID)))
    top, left = centre_offset(SENSOR, GRID)
    grid_weights[:, top:top + SENSOR[0], left:left + SENSOR[1]] = sensor_weights
    spectra = kernel_spectra(kernels, GRID)
    x = torch.as_tensor(rng.standard_normal((2, 1, *SENSOR)))
    small = eigen_kernel_forward(x, spectra, sensor_weights, GRID, convention)
    big = padded_scene_forward(pad(x, GRID), spectra,
                               sensor_weights if convention == "sensor" else grid_weights,
                               SENSOR, convention)
    torch.testing.assert_close(big, small, rtol=0, atol=1e-12)


class _TinyOperator:
    """Eq. 7 on the padded grid with the crop, bound to random kernels (for the norm tests)."""

    def __init__(self, convention: str, seed: int = 7) -> None:
        rng = np.random.default_rng(seed)
        self.channels, self.dtype = 2, torch.float64
        kernels = torch.as_tensor(rng.random((3, 2, 3, 4)))
        self.spectra = kernel_spectra(kernels, GRID)
        self.weights = torch.as_tensor(rng.random((3, *(SENSOR if convention == "sensor"
                                                         else GRID))))
        self.convention = convention
        self.calls = 0

    def domain_shape(self):
        return (1, self.channels, *GRID)

    def A(self, x):
        self.calls += 1
        return padded_scene_forward(x, self.spectra, self.weights, SENSOR, self.convention)

    def A_adjoint(self, y):
        return padded_scene_adjoint(y, self.spectra.conj(), self.weights, GRID, self.convention)

    def matrix(self) -> np.ndarray:
        n = 2 * GRID[0] * GRID[1]
        basis = torch.eye(n, dtype=torch.float64).reshape(n, 2, *GRID)
        return self.A(basis).reshape(n, -1).numpy().T           # (measurements, scene pixels)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_operator_norm_is_the_largest_singular_value_of_the_cropped_operator(convention):
    op = _TinyOperator(convention)
    sigma = np.linalg.svd(op.matrix(), compute_uv=False)[0]
    estimate = operator_norm(op, tol=1e-8, max_iterations=5000)
    # power iteration from below, to its tolerance
    assert estimate <= sigma * (1 + 1e-12)
    assert estimate == pytest.approx(sigma, rel=1e-6)
    # the default tolerance (1e-3)
    default = operator_norm(op)
    assert default <= sigma * (1 + 1e-12) and default == pytest.approx(sigma, rel=1e-3)
    # the crop lowers the norm below the kernels' spectral gain on the padded grid
    gain = float((op.spectra.abs() ** 2).sum(dim=0).amax().sqrt()) * float(op.weights.max())
    assert sigma < gain
    # cached on the operator (no A applied the second time) and deterministic
    calls = op.calls
    assert operator_norm(op) == default and op.calls == calls
    assert operator_norm(_TinyOperator(convention)) == default


def test_largest_eigenvalue_per_block_of_a_block_diagonal_operator():
    rng = np.random.default_rng(2)
    blocks = [rng.standard_normal((6, 6)) for _ in range(3)]
    blocks = [torch.as_tensor(b @ b.T) for b in blocks]           # PSD, one per channel

    def normal(v):                                                # v (2, 3, 6)
        return torch.stack([v[:, c] @ blocks[c].T for c in range(3)], dim=1)

    values = largest_eigenvalue(normal, (2, 3, 6), torch.float64, block_dim=1, tol=1e-10,
                                max_iterations=10000)
    expected = [float(torch.linalg.eigvalsh(b)[-1]) for b in blocks]
    np.testing.assert_allclose(values.numpy(), expected, rtol=1e-6)


# --- the operator of a kernel file (one place) and the base class of every operator ---------

def _kernel_model(basis: str, convention: str, seed: int = 4):
    from psfkit.forward.kernelfile import KernelModel

    rng = np.random.default_rng(seed)
    n = 1 if basis == "si" else 3
    kernels = (rng.random((n, 1, 3, 4)) ** 2).astype(np.float32)
    return KernelModel(kernels=kernels, basis=basis, convention=convention, sensor_shape=SENSOR,
                       channels=("L",))


KINDS = [("si", "sensor"), ("paper", "sensor"), ("paper", "source")]


def _operators(basis: str, convention: str, dtype: torch.dtype):
    """Every operator of the forward model, built from one kernel model (or its scenes)."""
    from psfkit.forward import PaddedSceneOperator, SpectralOperator

    model = _kernel_model(basis, convention)
    scenes = torch.rand((3, 1, *SENSOR), generator=torch.Generator().manual_seed(2),
                        dtype=torch.float64).to(dtype)
    return {"sensor-sized": SpectralOperator.from_kernel_model(model, dtype),
            "padded scene": PaddedSceneOperator.from_kernel_model(model, dtype),
            "kernel space": KernelSpaceOperator(scenes, basis, convention, (3, 4))}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize(("basis", "convention"), KINDS)
def test_every_operator_passes_the_base_class_adjointness_test(basis, convention, dtype):
    tol = {torch.float32: 1e-6, torch.float64: 1e-14}[dtype]
    for name, op in _operators(basis, convention, dtype).items():
        assert op.adjointness_error() < tol, name
        assert op.adjointness_error(seed=5) < tol, name
    # the test sees a wrong adjoint: Aᵀ of the transposed kernels is not the adjoint
    from psfkit.forward import SpectralOperator

    op = SpectralOperator.from_kernel_model(_kernel_model(basis, convention), dtype)
    op.A_adjoint = op.A                                            # type: ignore[method-assign]
    assert op.adjointness_error() > 1e-2


@pytest.mark.parametrize(("basis", "convention"), KINDS)
def test_kernel_file_operator_is_eq7_its_dense_matrix_and_its_norm(basis, convention):
    """Both operators of a kernel file against Eq. 7 written out pixel by pixel
    (:func:`_dense_reference`), and ``norm()`` against the dense matrix's SVD."""
    ops = _operators(basis, convention, torch.float64)
    model = _kernel_model(basis, convention)
    kernels = model.kernels.astype(np.float64)
    weights = model.weight_maps(extent=GRID) if convention == "source" else model.weight_maps()
    rng = np.random.default_rng(8)
    big = rng.standard_normal((2, 1, *GRID))
    reference = _dense_reference(big, kernels, weights, convention)
    padded = ops["padded scene"].A(torch.as_tensor(big)).numpy()
    np.testing.assert_allclose(padded, reference, rtol=0, atol=1e-12)
    small = rng.standard_normal((2, 1, *SENSOR))
    reference = _dense_reference(pad(torch.as_tensor(small), GRID).numpy(), kernels, weights,
                                 convention)
    sized = ops["sensor-sized"].A(torch.as_tensor(small)).numpy()
    np.testing.assert_allclose(sized, reference, rtol=0, atol=1e-12)
    for name, op in ops.items():
        n = int(np.prod(op.domain_shape()))
        eye = torch.eye(n, dtype=torch.float64)
        dense = np.stack([op.A(e.reshape(op.domain_shape())).numpy().ravel() for e in eye],
                         axis=1)                                   # column j = A e_j
        sigma = np.linalg.svd(dense, compute_uv=False)[0]
        assert op.norm(tol=1e-8, max_iterations=5000) == pytest.approx(sigma, rel=1e-6), name
        assert op.norm() <= sigma * (1 + 1e-12), name


def test_a_subset_of_the_kernel_space_operator_measures_its_own_norm():
    x = torch.rand((4, 1, *SENSOR), generator=torch.Generator().manual_seed(3),
                   dtype=torch.float64)
    whole = KernelSpaceOperator(x, "paper", "sensor", (3, 4))
    part = whole.subset(slice(0, 1))
    alone = KernelSpaceOperator(x[:1], "paper", "sensor", (3, 4))
    assert whole.norm() > part.norm() == pytest.approx(alone.norm(), rel=1e-12)


@pytest.mark.parametrize("start", [(0, 0), (-2, -3), (4, 5), (-7, 1)])
def test_a_cropped_inverse_fft_is_the_wrapped_block_of_the_whole_one(start):
    """``irfft2`` computing only a block (wrapping around the grid from ``start``) gives the
    block of the whole inverse, for an odd and an even width; and the centred kernel window
    computed that way (the kernel fits' inverse), and ``extract_kernel``'s of the whole inverse,
    are the whole inverse rolled to the kernel's centre and cut."""
    from psfkit.forward.convolution import kernels_from_spectra
    from psfkit.forward.fft import irfft2

    for grid in ((9, 12), (10, 11)):
        z = torch.rand((2, 3, *grid), generator=torch.Generator().manual_seed(0),
                       dtype=torch.float64)
        spectrum = rfft2(z)
        whole = torch.fft.irfft2(spectrum, s=grid)
        rolled = torch.roll(whole, shifts=(-start[0], -start[1]), dims=(-2, -1))
        block = irfft2(spectrum, grid, (6, 8), start=start)
        assert torch.allclose(block, rolled[..., :6, :8], atol=1e-13), (grid, start)
        assert torch.allclose(block, z.roll((-start[0], -start[1]), (-2, -1))[..., :6, :8],
                              atol=1e-13)
        for kernel_shape in ((5, 7), (6, 8), (1, 1)):
            # the centred window, by rolling the origin to the kernel's centre pixel
            origin = (kernel_shape[0] // 2, kernel_shape[1] // 2)
            expected = torch.roll(whole, origin, dims=(-2, -1))[..., :kernel_shape[0],
                                                                 :kernel_shape[1]]
            got = kernels_from_spectra(spectrum, grid, kernel_shape)
            assert got.shape == expected.shape
            assert torch.allclose(got, expected, atol=1e-13), (grid, kernel_shape)
            assert torch.equal(extract_kernel(whole, kernel_shape), expected)


def test_the_kernel_space_forward_leaves_its_cached_scene_spectra_as_they_were():
    """The source side sums the kernels' products into a new array: the cached (weighted)
    scene spectra are read, never overwritten (a second pass gives the same predictions)."""
    x = torch.rand((2, 3, *SENSOR), generator=torch.Generator().manual_seed(5),
                   dtype=torch.float64)
    op = KernelSpaceOperator(x, "paper", "source", (3, 4))
    cached = op.scene_spectra.clone()
    kernels = torch.rand(op.domain_shape(), generator=torch.Generator().manual_seed(6),
                         dtype=torch.float64)
    first = op.A(kernels)
    assert torch.equal(op.scene_spectra, cached)
    assert torch.equal(op.A(kernels), first)
