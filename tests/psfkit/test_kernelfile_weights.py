"""Weight bases (Eq. 7 and richer) and the kernel file hand-off format."""

import json

import numpy as np
import pytest

from psfkit.errors import ConfigurationError, ModelFileError
from psfkit.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.weights import BASIS_NAMES, get_basis, normalized_coordinates


def test_normalized_coordinates_reach_plus_minus_one_at_the_edges():
    u, v = normalized_coordinates((4, 6))
    assert u.shape == v.shape == (4, 6)
    np.testing.assert_allclose(u[0], (np.arange(6) - 2.5) / 3)
    np.testing.assert_allclose(v[:, 0], (np.arange(4) - 1.5) / 2)
    # with an explicit centre and on a padded (scene) grid
    u, v = normalized_coordinates((4, 6), optical_center=(1.0, 2.0), extent=(8, 12))
    assert u.shape == (8, 12)
    assert u[0, 3 + 2] == 0.0 and v[2 + 1, 0] == 0.0


def test_paper_weights_are_eq7():
    basis = get_basis("paper")
    assert basis.kernel_names == ("base", "v", "h")
    maps = basis.maps((9, 11))
    u, v = normalized_coordinates((9, 11))
    wh = 0.5 * np.sin(0.5 * np.pi * u) ** 2
    wv = 0.5 * np.sin(0.5 * np.pi * v) ** 2
    np.testing.assert_allclose(maps[1], wv)
    np.testing.assert_allclose(maps[2], wh)
    np.testing.assert_allclose(maps[0], 1 - wh - wv)
    assert maps.min() >= 0 and maps.max() <= 1
    assert maps[0, 4, 5] == 1.0  # optical centre: base kernel only


@pytest.mark.parametrize("name", BASIS_NAMES)
def test_every_basis_sums_to_one(name):
    maps = get_basis(name).maps((7, 10))
    np.testing.assert_allclose(maps.sum(axis=0), 1.0, atol=1e-12)
    assert maps.shape[0] == get_basis(name).n_kernels


def test_odd_terms_see_left_right_asymmetry_that_sin2_cannot():
    maps = get_basis("paper+odd").maps((5, 9))
    assert np.allclose(maps[2], maps[2][:, ::-1])            # Wh even in u
    assert np.allclose(maps[4], -maps[4][:, ::-1])           # h_odd odd in u
    assert get_basis("poly:2").kernel_names == ("base", "u1v0", "u0v1", "u2v0", "u1v1", "u0v2")


def test_unknown_basis():
    with pytest.raises(ConfigurationError, match="unknown weight basis 'papr'"):
        get_basis("papr")


def _model(**kw):
    rng = np.random.default_rng(0)
    return KernelModel(kernels=rng.random((3, 3, 8, 10)), sensor_shape=(8, 10), **kw)


def test_kernel_file_round_trip(tmp_path):
    model = _model(provenance={"grid": "lab/grid"}, normalization="base sums to 1")
    path = save_kernels(tmp_path / "k.npz", model)
    back = load_kernels(path)
    np.testing.assert_array_equal(back.kernels, model.kernels)
    assert back.kernels.dtype == np.float32
    assert (back.basis, back.convention, back.sensor_shape) == ("paper", "sensor", (8, 10))
    assert back.provenance == {"grid": "lab/grid"}
    assert back.weight_maps().shape == (3, 8, 10)
    si = KernelModel.shift_invariant(np.ones((1, 8, 10)), sensor_shape=(8, 10))
    back = load_kernels(save_kernels(tmp_path / "si.npz", si))
    assert back.kernel_names == ("base",) and back.channels == ("L",)
    np.testing.assert_array_equal(back.weight_maps(), np.ones((1, 8, 10)))


def _rewrite(path, kernels=None, **meta_changes):
    with np.load(path) as d:
        k = d["kernels"] if kernels is None else kernels
        meta = json.loads(str(d["metadata"]))
    meta.update(meta_changes)
    np.savez(path, kernels=k, metadata=np.array(json.dumps(meta)))


@pytest.mark.parametrize("change,message", [
    (dict(version=2), "kernel file version 2 is not supported"),
    (dict(format="other"), "not an ekdun-kernels file"),
    (dict(basis="paper+odd"), "basis 'paper\\+odd' needs 5 kernels"),
    (dict(convention="lens"), "convention must be 'sensor' or 'source'"),
    (dict(channels=["L"]), "kernels have 3 channel\\(s\\) but channels are \\['L'\\]"),
    (dict(kernels=np.zeros((3, 3, 9, 10), np.float32)), "larger than the sensor 8x10"),
    (dict(kernels=np.full((3, 3, 8, 10), np.nan, np.float32)), "NaN/Inf"),
    (dict(kernel_names=["base", "h", "v"]), "kernel_names .* do not match"),
])
def test_kernel_file_refuses_wrong_version_or_shape(tmp_path, change, message):
    path = save_kernels(tmp_path / "k.npz", _model())
    kernels = change.pop("kernels", None)
    _rewrite(path, kernels, **change)
    with pytest.raises(ModelFileError, match=message) as info:
        load_kernels(path)
    assert str(info.value).startswith(str(path))


def test_kernel_file_refuses_foreign_files(tmp_path):
    (tmp_path / "x.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(ModelFileError, match="not a readable kernel file"):
        load_kernels(tmp_path / "x.npz")
    np.savez(tmp_path / "y.npz", weights=np.zeros(3))
    with pytest.raises(ModelFileError, match="not a kernel file"):
        load_kernels(tmp_path / "y.npz")
    obj = np.empty(1, dtype=object)
    obj[0] = {"evil": 1}
    np.savez(tmp_path / "z.npz", kernels=obj, metadata=np.array("{}"))
    with pytest.raises(ModelFileError, match="not a readable kernel file"):
        load_kernels(tmp_path / "z.npz")  # pickled objects are never loaded
    with pytest.raises(ModelFileError, match="no such kernel file"):
        load_kernels(tmp_path / "missing.npz")
