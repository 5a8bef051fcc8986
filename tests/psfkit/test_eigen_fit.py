"""Eigen-kernel fits: exact recovery of known kernels, both conventions, CV, PCA, refusals."""

import numpy as np
import pytest
from scipy import ndimage

from psfkit.errors import InvalidInputError
from psfkit.fitting.grid.design import check_design, position_weights, predict_aligned
from psfkit.fitting.grid.eigen import DEFAULT_RIDGE, NormalEquations
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.fitting.grid.pca import principal_angles_deg, stack_pca
from psfkit.forward.weights import get_basis
from psfkit.io import GridWriter, read_grid

SHAPE = (3, 40, 48)


def _kernels(n_kernels, seed=0, variation=0.15):
    """Smooth, PSF-like kernels (support in the middle): a base kernel and corrections that
    differ from it by ``variation`` (as measured eigen-kernels do)."""
    rng = np.random.default_rng(seed)
    c, h, w = SHAPE
    # compact support (central 16 × 20 px) so that every shifted PSF stays on the sensor
    window = np.zeros((h, w))
    window[12:28, 14:34] = np.hanning(16)[:, None] * np.hanning(20)[None]

    def smooth():
        return ndimage.gaussian_filter(rng.random((c, h, w)), (0, 2, 2)) * window

    base = smooth()
    return np.stack([base] + [base + variation * smooth() for _ in range(n_kernels - 1)])


def _grid_shifts(n=5, step=(6, 5)):
    offsets = np.arange(n) - n // 2
    vv, uu = np.meshgrid(offsets * step[1], offsets * step[0], indexing="ij")
    return np.stack([uu, vv], axis=-1).reshape(-1, 2).astype(float)


@pytest.mark.parametrize("convention", ["sensor", "source"])
@pytest.mark.parametrize("basis_name", ["paper", "paper+odd+cross"])
def test_known_kernels_are_recovered_to_machine_precision(convention, basis_name):
    basis = get_basis(basis_name)
    truth = _kernels(basis.n_kernels)
    eq = NormalEquations(basis, convention, SHAPE)
    rng = np.random.default_rng(1)
    for shift in _grid_shifts():
        aligned = predict_aligned(truth, basis, tuple(shift), convention)
        valid = rng.random(SHAPE[1:]) > 0.05            # some pixels missing everywhere
        eq.add(aligned, valid, tuple(shift))
    kernels, conditioning = eq.solve(ridge=0.0)
    constrained = conditioning > 1e-6
    err = np.abs(kernels - truth)[..., constrained].max() / np.abs(truth).max()
    assert err < 1e-9


def _unblocked_normal_equations(basis, convention, images, valids, shifts):
    """The normal equations summed over whole images, one product at a time (the code before
    the cache-blocked accumulation), and the per-pixel LAPACK solve."""
    k = basis.n_kernels
    iu = np.triu_indices(k)
    c, h, w = images[0].shape
    gram = np.zeros((len(iu[0]), h, w), images[0].dtype)
    rhs = np.zeros((c, k, h, w), images[0].dtype)
    for image, valid, shift in zip(images, valids, shifts, strict=True):
        weights = position_weights(basis, (h, w), tuple(shift), convention).astype(image.dtype)
        mask = valid.astype(image.dtype)
        mw = weights * mask
        for index, (i, j) in enumerate(zip(*iu, strict=True)):
            gram[index] += mw[i] * weights[j]
        for ch in range(c):
            for kk in range(k):
                rhs[ch, kk] += weights[kk] * (image[ch] * mask)
    full = np.zeros((h * w, k, k))
    flat = gram.reshape(len(iu[0]), -1).T
    full[:, iu[0], iu[1]] = flat
    full[:, iu[1], iu[0]] = flat
    scale = np.maximum(np.trace(full, axis1=1, axis2=2) / k, 1e-300)
    prior = sum(np.outer(e, e) for e in (np.eye(k)[j] - np.eye(k)[0] for j in range(1, k)))
    # the library's default ridge, as NormalEquations.solve() uses it
    system = full / scale[:, None, None] + DEFAULT_RIDGE * prior + 1e-12 * np.eye(k)
    b = rhs.reshape(c, k, -1).transpose(2, 1, 0) / scale[:, None, None]
    solution = np.linalg.solve(system, b)
    return gram, rhs, np.moveaxis(solution, 0, -1).reshape(k, c, h, w)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_blocked_accumulation_and_vectorized_solve_match_the_whole_image_path(convention):
    """float32 grid data, a shape taller than one block of rows, some pixels never seen:
    the sums are bit-identical and the kernels equal to the LAPACK solve to 1e-5."""
    basis = get_basis("paper")
    rng = np.random.default_rng(4)
    shape = (3, 70, 300)                      # 300 px rows: 54 rows per block, two blocks
    truth = np.abs(rng.normal(size=(basis.n_kernels, *shape)))
    shifts = _grid_shifts(n=5, step=(20, 9))
    images, valids = [], []
    for shift in shifts:
        images.append((predict_aligned(truth, basis, tuple(shift), convention)
                       + 0.01 * rng.normal(size=shape)).astype(np.float32))
        valid = rng.random(shape[1:]) > 0.1
        valid[:, :5] = False                  # unconstrained columns: the ridge decides
        valids.append(valid)
    eq = NormalEquations(basis, convention, shape)
    for image, valid, shift in zip(images, valids, shifts, strict=True):
        eq.add(image, valid, tuple(shift))
    gram, rhs, reference = _unblocked_normal_equations(basis, convention, images, valids,
                                                       shifts)
    assert np.array_equal(eq.gram, gram) and np.array_equal(eq.rhs, rhs)
    kernels = eq.solve(conditioning=False)[0]
    assert np.abs(kernels - reference).max() <= 1e-5 * np.abs(reference).max()


def _rectangle_mask(shape, rng):
    valid = np.zeros(shape, bool)
    valid[rng.integers(0, 8):shape[0] - rng.integers(0, 8),
          rng.integers(0, 8):shape[1] - rng.integers(0, 8)] = True
    return valid


@pytest.mark.parametrize("convention", ["sensor", "source"])
@pytest.mark.parametrize("basis_name", ["paper", "paper+odd+cross", "poly:2"])
def test_rectangle_masks_give_the_whole_image_sums(convention, basis_name):
    """Rectangular valid masks take the factored path (Gram sums as matrix products, base
    right-hand side from the masked image): the same sums as the per-pixel products, mixed
    with PSFs that take the masked path, and through the cross-validation's minus/plus."""
    basis = get_basis(basis_name)
    rng = np.random.default_rng(7)
    shape = (2, 37, 300)                       # wider than a block: several row blocks
    shifts = _grid_shifts(n=4, step=(25, 7))
    images, valids = [], []
    for p in range(len(shifts)):
        images.append(rng.random(shape))
        valid = _rectangle_mask(shape[1:], rng)
        if p % 5 == 0:                         # some masks with holes: the per-pixel path
            valid &= rng.random(shape[1:]) > 0.1
        valids.append(valid)
    eq = NormalEquations(basis, convention, shape)
    for image, valid, shift in zip(images, valids, shifts, strict=True):
        eq.add(image, valid, tuple(shift))
    gram, rhs, kernels = _unblocked_normal_equations(basis, convention, images, valids, shifts)
    np.testing.assert_allclose(eq.gram, gram, rtol=1e-12, atol=1e-12 * np.abs(gram).max())
    np.testing.assert_allclose(eq.rhs, rhs, rtol=1e-12, atol=1e-12 * np.abs(rhs).max())
    assert eq.count == len(shifts)
    solved, smallest = eq.solve()
    well_posed = smallest > 1e-4    # small shifts: weights barely vary at many pixels
    assert well_posed.mean() > 0.2
    assert np.abs(solved - kernels)[..., well_posed].max() <= \
        1e-8 * np.abs(kernels)[..., well_posed].max()
    # a fold: all PSFs minus a group equals the equations of the rest
    group = NormalEquations(basis, convention, shape)
    rest = NormalEquations(basis, convention, shape)
    for p, (image, valid, shift) in enumerate(zip(images, valids, shifts, strict=True)):
        (group if p % 3 == 0 else rest).add(image, valid, tuple(shift))
    difference = eq.minus(group)
    np.testing.assert_allclose(difference.gram, rest.gram, atol=1e-12 * np.abs(gram).max())
    np.testing.assert_allclose(difference.rhs, rest.rhs, atol=1e-12 * np.abs(rhs).max())
    rest += group
    np.testing.assert_allclose(rest.rhs, rhs, atol=1e-12 * np.abs(rhs).max())
    assert rest.count == len(shifts)


@pytest.mark.parametrize("convention", ["sensor", "source"])
def test_known_kernels_are_recovered_through_rectangle_masks(convention):
    basis = get_basis("paper+odd+cross")
    truth = _kernels(basis.n_kernels)
    eq = NormalEquations(basis, convention, SHAPE)
    rng = np.random.default_rng(2)
    for shift in _grid_shifts():
        eq.add(predict_aligned(truth, basis, tuple(shift), convention),
               _rectangle_mask(SHAPE[1:], rng), tuple(shift))
    kernels, conditioning = eq.solve(ridge=0.0)
    constrained = conditioning > 1e-6
    assert constrained.mean() > 0.5
    err = np.abs(kernels - truth)[..., constrained].max() / np.abs(truth).max()
    assert err < 1e-9


def test_float32_gram_sums_stay_positive_semidefinite_where_one_psf_is_seen():
    """A pixel seen by a single PSF has a rank-one Gram matrix: float64 matrix products keep
    it positive semi-definite (float32 sums did not), so the ridge sets its kernels calmly."""
    basis = get_basis("paper")
    shape = (1, 20, 30)
    rng = np.random.default_rng(0)
    eq = NormalEquations(basis, "sensor", shape)
    for shift in _grid_shifts(n=3, step=(4, 3)):
        valid = np.zeros(shape[1:], bool)
        valid[:, 5:] = True
        if shift[0] < 0:
            valid[:, :] = True           # only these PSFs see the first five columns
        if shift[0] < 0 and shift[1] != 0:
            continue
        eq.add(rng.random(shape).astype(np.float32), valid, tuple(shift))
    _, smallest = eq.solve()
    assert smallest is not None and smallest.min() > -1e-12


def test_the_other_convention_does_not_fit_exactly():
    basis = get_basis("paper")
    truth = _kernels(3)
    shifts = _grid_shifts()
    residual = {}
    for fit_convention in ("sensor", "source"):
        eq = NormalEquations(basis, fit_convention, SHAPE)
        data = [predict_aligned(truth, basis, tuple(s), "sensor") for s in shifts]
        for s, a in zip(shifts, data, strict=True):
            eq.add(a, np.ones(SHAPE[1:], bool), tuple(s))
        kernels = eq.solve(ridge=0.0)[0]
        residual[fit_convention] = max(
            np.linalg.norm(predict_aligned(kernels, basis, tuple(s), fit_convention) - a)
            / np.linalg.norm(a) for s, a in zip(shifts, data, strict=True))
    assert residual["sensor"] < 1e-9
    assert residual["source"] > 1e-3


def test_sensor_and_source_weights_live_where_they_should():
    basis = get_basis("paper")
    w_sensor = position_weights(basis, (40, 48), (6.0, -5.0), "sensor")
    w_source = position_weights(basis, (40, 48), (6.0, -5.0), "source")
    assert w_sensor.shape == (3, 40, 48) and w_source.shape == (3, 1, 1)
    # the sensor-side weight at aligned pixel v is the weight map at sensor pixel v + s
    maps = basis.maps((40, 48))
    np.testing.assert_allclose(w_sensor[:, 10, 10], maps[:, 10 - 5, 10 + 6], atol=1e-12)
    # the source-side weight is the map at the source's own pixel (kernel origin + s)
    np.testing.assert_allclose(w_source[:, 0, 0], maps[:, 20 - 5, 24 + 6], atol=1e-12)


def test_design_refusals():
    basis = get_basis("paper")
    row = np.stack([np.arange(-2, 3) * 6.0, np.zeros(5)], axis=-1)
    with pytest.raises(InvalidInputError, match=r"singular design: the weight of kernel 'v'"):
        check_design(basis, row, (40, 48), "grid")
    with pytest.raises(InvalidInputError,
                       match=r"needs at least 10 positions \(10 kernels\) but only 9 remain"):
        check_design(get_basis("poly:3"), _grid_shifts(3), (40, 48), "grid")
    check_design(basis, _grid_shifts(3), (40, 48), "grid")


def _write_synthetic_grid(path, truth, basis, convention, shifts, n):
    _, h, w = SHAPE
    with GridWriter(path, (n, n), suffix=".npy") as writer:
        for index, s in enumerate(shifts):
            aligned = predict_aligned(truth, basis, tuple(s), convention)
            image = np.zeros(SHAPE)
            du, dv = int(s[0]), int(s[1])            # integer shifts: exact, no interpolation
            src = aligned[:, max(0, -dv):h - max(0, dv), max(0, -du):w - max(0, du)]
            image[:, max(0, dv):max(0, dv) + src.shape[1],
                  max(0, du):max(0, du) + src.shape[2]] = src
            writer.add(index // n, index % n, (image * 1000).astype(np.float32),
                       monitor_px=(-s[0] / 6 * 10, -s[1] / 5 * 10))


def test_fit_eigen_grid_end_to_end_on_a_synthetic_grid(tmp_path):
    basis = get_basis("paper")
    truth = _kernels(3, seed=3)
    shifts = _grid_shifts()
    _write_synthetic_grid(tmp_path / "g", truth, basis, "sensor", shifts, 5)
    result = fit_eigen_grid(read_grid(tmp_path / "g"),
                            EigenFitOptions(convention="sensor", working_size=64))
    np.testing.assert_allclose(result.shifts.reshape(-1, 2), shifts, atol=0.1)
    # kernels are in the grid's normalization (centre PSF peak = 1): compare shapes
    fitted = result.full_kernels["sensor"]
    inner = (slice(None), slice(None), slice(8, -8), slice(8, -8))
    diff = (fitted / fitted[0].max() - truth / truth[0].max())[inner]
    # registration of PSFs that differ from the centre one is good to ~0.05 px, which bounds
    # the end-to-end accuracy (the solver alone is exact: see the machine-precision test)
    assert np.linalg.norm(diff) / np.linalg.norm((truth / truth[0].max())[inner]) < 0.05
    assert np.abs(diff).max() < 0.08
    cv = result.cv["held_out_relative_error"]
    assert cv["paper/sensor"] < 0.3 * cv["centre PSF only"]
    model = result.kernel_model()
    assert model.kernels.shape == (3, 3, 40, 48) and model.basis == "paper"
    assert model.kernels[0].sum(axis=(1, 2)).mean() == pytest.approx(1.0, rel=1e-6)


def test_pca_and_principal_angles():
    rng = np.random.default_rng(0)
    basis_images = rng.normal(size=(3, 1, 10, 12))
    coefficients = rng.normal(size=(20, 3))
    images = np.einsum("pk,kchw->pchw", coefficients, basis_images)
    valid = np.ones((20, 10, 12), bool)
    result = stack_pca(images, valid)
    assert result.explained[2] == pytest.approx(1.0, abs=1e-12)
    assert result.explained[1] < 0.999
    angles = principal_angles_deg(basis_images, result.components[:3])
    assert np.all(angles < 1e-5)
    other = rng.normal(size=(3, 1, 10, 12))
    assert principal_angles_deg(basis_images, other).max() > 30


def test_bench_grid_eigen_kernels_predict_held_out_positions_better(bench_grid_ds2):
    """On the virtual bench the fitted model beats the centre PSF and one shift-invariant
    kernel on positions it never saw, and the kernels carry the grid's real variation."""
    result = fit_eigen_grid(read_grid(bench_grid_ds2), EigenFitOptions(folds=6))
    cv = result.cv["held_out_relative_error"]
    for convention in ("sensor", "source"):
        assert cv[f"paper/{convention}"] < 0.8 * cv["centre PSF only"]
        assert cv[f"paper/{convention}"] < cv[f"si/{convention}"]
    kernels = result.kernels
    difference = np.linalg.norm(kernels[1] - kernels[0]) / np.linalg.norm(kernels[0])
    assert 1e-3 < difference < 0.5
    assert result.pca.explained[0] > 0.9                # the mean PSF dominates
    assert result.angles_deg[0] < 5.0                   # Kbase ≈ the first PCA direction
