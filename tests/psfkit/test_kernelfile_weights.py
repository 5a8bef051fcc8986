"""Weight bases (Eq. 7 and richer) and the kernel file hand-off format."""

import json

import numpy as np
import pytest

from psfkit.errors import ConfigurationError, ModelFileError, PsfkitError
from psfkit.forward.kernel_checks import check_kernels
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.forward.weights import BASIS_NAMES, get_basis
from tests.helpers.weights import normalized_coordinates


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


@pytest.mark.parametrize("name", BASIS_NAMES)
def test_every_weight_is_the_product_of_its_row_and_column_factors(name):
    # the eigen-kernel fit sums Gram terms as matrix products of these factors
    basis = get_basis(name)
    u = np.linspace(-1.3, 1.2, 17)
    v = np.linspace(-1.1, 1.4, 11)
    for term in basis.terms:
        fu, fv = term.factors(u, v)
        fu = np.ones_like(u) if fu is None else fu
        fv = np.ones_like(v) if fv is None else fv
        expected = np.broadcast_to(term(u[None, :], v[:, None]), (len(v), len(u)))
        np.testing.assert_allclose(fv[:, None] * fu[None, :], expected, rtol=1e-14, atol=1e-15)


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


@pytest.mark.parametrize("change,message", [
    (dict(kernels=np.full((3, 3, 8, 10), np.nan)), "kernel model: kernels contain NaN/Inf"),
    (dict(kernels=np.ones((3, 8, 10))), r"kernels must be \(K, C, H, W\), got shape"),
    (dict(kernels=np.ones((3, 3, 8, 11))), "kernels 8x11 are larger than the sensor 8x10"),
    (dict(kernels=np.ones((2, 3, 8, 10))), "basis 'paper' needs 3 kernels"),
    (dict(kernels=np.full((3, 3, 8, 10), "a")), "kernels must be real numbers"),
    (dict(convention="lens"), "convention must be 'sensor' or 'source', got 'lens'"),
    (dict(basis="papr"), "unknown weight basis 'papr'"),
    (dict(channels=("R", "G")), r"kernels have 3 channel\(s\) but channels are"),
    (dict(sensor_shape=(8.0, 10.0)), r"sensor_shape \[8.0, 10.0\] is not a valid size"),
    (dict(sensor_shape=(8, 10, 1)), "sensor_shape .* is not a valid size"),
    (dict(scene_padding=1), "scene_padding must be an integer in 2...8, got 1"),
    (dict(scene_padding=2.0), "scene_padding must be an integer in 2...8, got 2.0"),
    (dict(optical_center=(np.nan, 1.0)), "optical_center must be None or two finite numbers"),
    (dict(optical_center=(1.0,)), "optical_center must be None or two finite numbers"),
])
def test_kernel_model_refuses_what_breaks_the_contract(change, message):
    values = dict(kernels=np.ones((3, 3, 8, 10), np.float32), sensor_shape=(8, 10))
    values.update(change)
    with pytest.raises(ModelFileError, match=message) as info:
        KernelModel(**values)
    assert isinstance(info.value, PsfkitError)           # the CLIs print it as one line


def test_validate_catches_kernels_changed_in_place_and_save_refuses_them(tmp_path):
    model = _model()
    model.validate()                                      # a valid model passes
    model.kernels[1, 2, 3, 4] = np.inf                    # the array is mutable
    with pytest.raises(ModelFileError, match=r"^seed: kernels contain NaN/Inf"):
        model.validate(where="seed")
    with pytest.raises(ModelFileError, match=r"k\.npz: kernels contain NaN/Inf"):
        save_kernels(tmp_path / "k.npz", model)
    assert list(tmp_path.iterdir()) == []                 # nothing written, not even a temp


def test_check_kernels_is_the_array_part_of_the_contract():
    check_kernels(np.zeros((1, 1, 4, 4), np.float64), (4, 4))
    with pytest.raises(ModelFileError, match=r"^kernels must be float32 or float64, got int64"):
        check_kernels(np.zeros((1, 1, 4, 4), np.int64), (4, 4))
    with pytest.raises(ModelFileError, match=r"^x: kernels must have at least one kernel"):
        check_kernels(np.zeros((0, 1, 4, 4)), (4, 4), where="x")

    class OtherError(PsfkitError):
        pass

    with pytest.raises(OtherError, match="kernels 5x4 are larger than the sensor 4x4"):
        check_kernels(np.zeros((1, 1, 5, 4)), (4, 4), error=OtherError)


def test_metadata_round_trip():
    model = _model(basis="paper", convention="source", optical_center=(np.float64(3.5), 4),
                   scene_padding=3, normalization="base sums to 1",
                   provenance={"grid": "lab/grid", "residual": 0.01})
    meta = model.to_metadata()
    assert json.loads(json.dumps(meta)) == meta           # JSON as it is
    assert meta["kernel_names"] == ["base", "v", "h"] and meta["format"] == "ekdun-kernels"
    back = KernelModel.from_metadata(model.kernels, meta)
    assert back.to_metadata() == meta
    np.testing.assert_array_equal(back.kernels, model.kernels)
    assert (back.basis, back.convention, back.sensor_shape, back.optical_center,
            back.scene_padding, back.normalization, back.provenance) == (
        "paper", "source", (8, 10), (3.5, 4.0), 3, "base sums to 1",
        {"grid": "lab/grid", "residual": 0.01})
    # numpy integers in the geometry are stored as ints (json.dumps refuses numpy's)
    numpy_shape = KernelModel(kernels=model.kernels, sensor_shape=(np.int64(8), np.int64(10)))
    assert json.dumps(numpy_shape.to_metadata()["sensor_shape"]) == "[8, 10]"


def test_from_metadata_reads_the_older_checkpoint_form_and_names_the_problem():
    # what ekdun checkpoints stored before the metadata had one writer: no format, version,
    # kernel_names or kernel_origin
    old = {"basis": "paper", "convention": "sensor", "sensor_shape": [8, 10],
           "channels": ["R", "G", "B"], "optical_center": None, "scene_padding": 2,
           "normalization": "unspecified", "provenance": {}}
    kernels = _model().kernels
    back = KernelModel.from_metadata(kernels, old)
    assert {k: v for k, v in back.to_metadata().items() if k in old} == old
    with pytest.raises(ModelFileError, match=r"^seed: metadata lacks 'convention'"):
        KernelModel.from_metadata(kernels, {k: v for k, v in old.items() if k != "convention"},
                                  where="seed")
    with pytest.raises(ModelFileError, match=r"^seed: kernels contain NaN/Inf"):
        KernelModel.from_metadata(np.full_like(kernels, np.nan), old, where="seed")
    with pytest.raises(ModelFileError, match=r"^seed: kernel_names .* do not match"):
        KernelModel.from_metadata(kernels, {**old, "kernel_names": ["a", "b", "c"]},
                                  where="seed")
    with pytest.raises(ModelFileError, match=r"^seed: metadata is not a JSON object"):
        KernelModel.from_metadata(kernels, ["paper"], where="seed")  # type: ignore[arg-type]


@pytest.mark.parametrize("basis", ["paper", "paper+odd+cross", "poly:2"])
def test_weight_maps_on_a_larger_grid_continue_the_edge_weights(basis):
    b = get_basis(basis)
    centre = (3.0, 4.5)                                     # off the sensor centre
    maps = b.maps((7, 10), centre)
    big = b.maps((7, 10), centre, extent=(14, 21))
    assert big.shape == (b.n_kernels, 14, 21)
    top, left = (14 - 7) // 2, (21 - 10) // 2               # where pad() puts the sensor
    np.testing.assert_array_equal(big[:, top:top + 7, left:left + 10], maps)
    np.testing.assert_array_equal(big[:, :top, left:left + 10],
                                  np.repeat(maps[:, :1], top, axis=1))
    np.testing.assert_array_equal(big[:, -1, -1], maps[:, -1, -1])
    with pytest.raises(ConfigurationError, match="smaller than the sensor"):
        b.maps((7, 10), extent=(6, 21))
