"""Datasets: dead leaves, the dense shift-variant model, the cached virtual bench, pairs."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from ekdun.data.deadleaves import dead_leaves
from ekdun.data.dense_model import DenseShiftVariantModel, hat_weights
from ekdun.data.pairs import PairsDataset, match_downsample, parse_names
from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench, read_manifest
from ekdun.errors import ConfigurationError, InvalidInputError
from ekdun.physics.operators import ShiftInvariantOperator
from psfkit.forward.kernelfile import KernelModel
from psfkit.io import read_grid
from psfkit.io.pairs import read_pairs

SMALL = VirtualBenchSpec(sensor_shape=(32, 32), n_train=3, n_test=2, grid_shape=(3, 3))


def radial_power_slope(image: np.ndarray, f_min: float = 0.02, f_max: float = 0.25) -> float:
    """Log-log slope of the radially averaged power spectrum of a ``(H, W)`` image between
    ``f_min`` and ``f_max`` cycles/pixel (natural images: about −2)."""
    img = np.asarray(image, dtype=np.float64)
    img = img - img.mean()
    power = np.abs(np.fft.fft2(img)) ** 2
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    f = np.sqrt(fy ** 2 + fx ** 2)
    edges = np.geomspace(f_min, f_max, 12)
    centres, means = [], []
    for lo, hi in itertools.pairwise(edges):
        sel = (f >= lo) & (f < hi)
        if sel.any():
            centres.append(np.sqrt(lo * hi))
            means.append(power[sel].mean())
    slope, _ = np.polyfit(np.log(centres), np.log(means), 1)
    return float(slope)


def test_dead_leaves_statistics():
    images = [dead_leaves((128, 128), seed) for seed in range(4)]
    for im in images:
        assert im.shape == (3, 128, 128) and im.dtype == np.float32
        assert 0.0 <= im.min() and im.max() <= 1.0
    # piecewise-constant disks: many exactly repeated values, sharp edges
    assert len(np.unique(images[0][0])) < 0.2 * 128 * 128
    # scale invariance: power spectrum close to 1/f^2 (natural images: slope about -2)
    slope = np.mean([radial_power_slope(im.mean(axis=0)) for im in images])
    assert -2.8 < slope < -1.2
    np.testing.assert_array_equal(dead_leaves((32, 32), 5), dead_leaves((32, 32), 5))


def test_scenes_do_not_depend_on_the_number_of_worker_processes(capsys):
    """make-dataset draws scenes in --threads processes: every scene has its own seed, so
    the split is the same array for one process or several (chunks of uneven size too); the
    progress bar counts every scene either way."""
    from ekdun.data.bench_spec import make_scenes

    spec = VirtualBenchSpec(sensor_shape=(32, 32), n_train=11, n_test=2)
    one = make_scenes(spec, "train")
    assert one.shape == (11, 3, 32, 32)
    assert capsys.readouterr().err == ""
    np.testing.assert_array_equal(make_scenes(spec, "train", workers=3, progress=True), one)
    final = capsys.readouterr().err.replace("\r", "\n").strip().splitlines()[-1]
    assert final.startswith("scenes (train)") and "11/11" in final
    assert not np.array_equal(make_scenes(spec, "train", stream=5), one)


def test_hat_weights_partition_of_unity():
    w = hat_weights(np.array([2.0, 10.0, 20.0]), 25)
    np.testing.assert_allclose(w.sum(axis=0), 1.0)
    assert w[0, 0] == 1.0 and w[2, 24] == 1.0 and w[1, 10] == 1.0
    assert w[0, 6] == pytest.approx(0.5) and w[1, 6] == pytest.approx(0.5)


@pytest.mark.parametrize("convention", ["source", "sensor"])
def test_dense_model_with_equal_psfs_is_the_shift_invariant_model(convention):
    rng = np.random.default_rng(0)
    k = rng.random((3, 12, 10))
    kernels = np.broadcast_to(k, (3, 4, 3, 12, 10))
    model = DenseShiftVariantModel(kernels, [3, 10, 20], [0, 5, 20, 30], (24, 32), convention)
    x = torch.rand(2, 3, 24, 32, dtype=torch.float64)
    si = ShiftInvariantOperator(torch.as_tensor(k), (24, 32)).double()
    torch.testing.assert_close(model(x), si.A(x), rtol=1e-10, atol=1e-12)


def test_point_source_at_a_node_images_to_that_nodes_psf():
    rng = np.random.default_rng(1)
    kernels = rng.random((3, 3, 1, 9, 9))
    rows, cols = [4, 12, 20], [5, 14, 25]
    model = DenseShiftVariantModel(kernels, rows, cols, (24, 30), "source")
    x = np.zeros((1, 24, 30))
    x[0, rows[1], cols[2]] = 1.0
    y = model(x).numpy()
    expected = np.zeros((1, 24, 30))
    expected[0, rows[1] - 4:rows[1] + 5, cols[2] - 4:cols[2] + 5] = kernels[1, 2, 0]
    np.testing.assert_allclose(y, expected, atol=1e-10)


def test_virtual_bench_is_deterministic_cached_and_rebuilt_on_mismatch(tmp_path):
    a = make_virtual_bench(tmp_path / "a", SMALL, progress=False)
    b = make_virtual_bench(tmp_path / "b", SMALL, progress=False)
    ma, mb = read_manifest(a), read_manifest(b)
    assert ma["content_hash"] == mb["content_hash"] and ma["files"] == mb["files"]
    assert ma["spec"]["seed"] == 0 and "torch" in ma["versions"]
    scene = np.load(a / "train" / "scene" / "train0000.npy")
    assert scene.shape == (32, 32, 3) and scene.dtype == np.float32
    # the grid is a psfkit grid of the requested shape (for psfkit fit-eigen / compare)
    assert read_grid(a / "grid").grid_shape == (3, 3)
    pairs = read_pairs(a / "test")
    assert len(pairs) == 2 and pairs.shape == (3, 32, 32)

    # cached: not rebuilt (the files keep their modification times)
    stamp = (a / "manifest.json").stat().st_mtime_ns
    make_virtual_bench(a, SMALL, progress=False)
    assert (a / "manifest.json").stat().st_mtime_ns == stamp
    # manifest disagrees (other spec) -> rebuilt; a corrupted file -> rebuilt
    other = VirtualBenchSpec(sensor_shape=(32, 32), n_train=3, n_test=1, grid_shape=(3, 3))
    make_virtual_bench(a, other, progress=False)
    assert read_manifest(a)["spec"]["n_test"] == 1 and len(read_pairs(a / "test")) == 1
    np.save(a / "train" / "scene" / "train0000.npy", np.zeros((32, 32, 3), np.float32))
    make_virtual_bench(a, other, progress=False)
    assert np.load(a / "train" / "scene" / "train0000.npy").max() > 0
    # a foreign non-empty folder is never overwritten
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(InvalidInputError, match="not a virtual-bench dataset"):
        make_virtual_bench(tmp_path / "mine", SMALL, progress=False)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"
    assert json.loads((a / "manifest.json").read_text())["format"] == "ekdun-virtual-bench"


def test_grid_frames_average_only_the_grid_and_older_manifests_stay_current(tmp_path):
    """``grid_frames`` changes the grid (float means, recorded), not the pairs; a manifest
    written before the field existed is current for the default spec (not rebuilt)."""
    from dataclasses import replace

    plain = make_virtual_bench(tmp_path / "plain", SMALL, progress=False)
    averaged = make_virtual_bench(tmp_path / "avg", replace(SMALL, grid_frames=4),
                                  progress=False)
    assert read_manifest(averaged)["spec"]["grid_frames"] == 4
    assert read_grid(plain / "grid").dtype == np.uint16
    assert read_grid(averaged / "grid").dtype == np.float32
    for name in ("train/scene/train0000.npy", "train/measurement/train0000.npy",
                 "grid/ground_truth/psfs_clean.npy"):
        np.testing.assert_array_equal(np.load(plain / name), np.load(averaged / name))
    doc = json.loads((plain / "manifest.json").read_text())
    del doc["spec"]["grid_frames"]
    (plain / "manifest.json").write_text(json.dumps(doc))
    stamp = (plain / "manifest.json").stat().st_mtime_ns
    make_virtual_bench(plain, SMALL, progress=False)
    assert (plain / "manifest.json").stat().st_mtime_ns == stamp
    with pytest.raises(ConfigurationError, match="grid_frames"):
        VirtualBenchSpec(grid_frames=0)


def test_bench_spec_round_trips_through_its_manifest_form():
    spec = VirtualBenchSpec(sensor_shape=(48, 32), grid_shape=(5, 7), photons=123.0, seed=4)
    doc = json.loads(json.dumps(spec.to_dict()))           # as a manifest stores it
    assert doc["sensor_shape"] == [48, 32] and "oracle" not in doc
    back = VirtualBenchSpec.from_dict(doc)
    assert back == spec and isinstance(back.grid_shape, tuple)


@pytest.mark.parametrize("with_oracle", [True, False])
def test_a_dataset_made_with_oracles_before_issue_44_still_reads_and_is_reused(
        tmp_path, with_oracle):
    """make-dataset wrote ``oracle/`` and the spec fields ``oracle``, ``oracle_scenes`` until
    issue 44: such a manifest still reads (the fields ignored) and the dataset, oracles
    included, is reused for the same spec instead of rebuilt; a changed byte still rebuilds."""
    from ekdun.data.virtual_bench import content_hash, dataset_is_current, resolve_split

    root = make_virtual_bench(tmp_path / "old", SMALL, progress=False)
    doc = json.loads((root / "manifest.json").read_text())
    # the manifest as make-dataset wrote it before: the old spec fields, the oracle files
    # listed and hashed with the rest, and their record
    doc["spec"].update(oracle=with_oracle, oracle_scenes=48 if with_oracle else 0)
    if with_oracle:
        (root / "oracle").mkdir()
        np.savez(root / "oracle" / "paper_source.npz", kernels=np.ones((3, 3, 32, 32)))
        doc["oracle"] = {"basis": "paper", "dense_convention": "source",
                         "files": {"source": {"operator": "paper_source.npz"}}}
        doc["files"] = sorted([*doc["files"], "oracle/paper_source.npz"])
        doc["content_hash"] = content_hash(root, doc["files"])
    (root / "manifest.json").write_text(json.dumps(doc))
    assert VirtualBenchSpec.from_dict(read_manifest(root)["spec"]) == SMALL
    assert dataset_is_current(root, SMALL)
    stamp = (root / "manifest.json").stat().st_mtime_ns
    assert make_virtual_bench(root, SMALL, progress=False) == root
    assert (root / "manifest.json").stat().st_mtime_ns == stamp
    assert (root / "oracle").is_dir() == with_oracle          # kept as it was
    assert resolve_split(root, "train") == root / "train"
    assert len(PairsDataset(root / "train")) == SMALL.n_train
    if with_oracle:   # the oracle files are part of the hashed content, as before
        np.savez(root / "oracle" / "paper_source.npz", kernels=np.zeros((3, 3, 32, 32)))
        assert not dataset_is_current(root, SMALL)


def test_pairs_dataset_reads_dlmd_as_rgb(real_data):
    root = real_data("dlmd_mirflickr")
    ds = PairsDataset(root)
    assert len(ds) == 7 and ds.image_shape == (3, 270, 480)
    scene, meas = ds[0]
    assert scene.shape == meas.shape == (3, 270, 480) and scene.dtype == torch.float32
    raw = np.load(root / "lensed" / f"{ds.names[0]}.npy")           # BGR on disk
    np.testing.assert_array_equal(scene.numpy(), np.moveaxis(raw[..., ::-1], -1, 0))


def _dlmd_like(root, names, shape=(3, 18, 30)):
    """A DLMD-layout folder (lensed/ + diffuser/, BGR HWC .npy) of random pairs."""
    rng = np.random.default_rng(3)
    for sub in ("lensed", "diffuser"):
        (root / sub).mkdir(parents=True)
        for name in names:
            np.save(root / sub / f"{name}.npy",
                    rng.random((shape[1], shape[2], shape[0])).astype(np.float32))
    return root


def test_pairs_dataset_holds_out_and_bins_like_fit_pairs(tmp_path):
    root = _dlmd_like(tmp_path / "d", ["a", "b", "c"])
    ds = PairsDataset(root, holdout=["b.npy"], downsample=4)
    assert ds.names == ("a", "c") and len(ds) == 2 and ds.image_shape == (3, 4, 7)
    scene, meas = ds[1]
    raw = np.moveaxis(np.load(root / "lensed" / "c.npy"), -1, 0)[::-1]        # BGR -> RGB
    expected = raw[:, :16, :28].reshape(3, 4, 4, 7, 4).mean(axis=(2, 4))
    np.testing.assert_allclose(scene.numpy(), expected, rtol=1e-6)
    assert meas.shape == scene.shape == (3, 4, 7)
    info = ds.describe()
    assert info["holdout"] == ["b"] and info["channel_order"] == "BGR"
    assert info["downsample"] == 4 and info["image_shape"] == [3, 4, 7]
    lazy = PairsDataset(root, holdout=["b"], downsample=4, preload=False)
    np.testing.assert_array_equal(lazy[1][0].numpy(), scene.numpy())
    with pytest.raises(InvalidInputError, match="no pair named zz"):
        PairsDataset(root, holdout=["zz"])
    with pytest.raises(InvalidInputError, match="every pair is held out"):
        PairsDataset(root, holdout=["a,b", "c"])
    with pytest.raises(InvalidInputError, match="too few pixels"):
        PairsDataset(root, downsample=5)
    assert parse_names(["im65,im157", " im65.npy"]) == ("im65", "im157")


def test_evaluation_scores_only_what_training_held_out(tmp_path):
    from ekdun.evaluation import evaluation_pairs

    root = _dlmd_like(tmp_path / "d", ["a", "b", "c"])
    trained = PairsDataset(root, holdout=["b"], downsample=4).describe()
    ds, note = evaluation_pairs(root, trained)
    assert ds.names == ("b",) and "held out: b" in note
    assert ds.image_shape == (3, 4, 7) and ds.pairs.channel_order == "BGR"   # read as trained
    np.testing.assert_array_equal(
        ds[0][0].numpy(), PairsDataset(root, downsample=4)[1][0].numpy())
    # the same folder named by another path is still the training folder
    ds, _ = evaluation_pairs(tmp_path / "d" / ".." / "d", trained)
    assert ds.names == ("b",)
    # a run trained on every pair cannot be scored on its own folder by accident
    everything = PairsDataset(root).describe()
    with pytest.raises(InvalidInputError, match="trained on every pair of this folder"):
        evaluation_pairs(root, everything)
    ds, note = evaluation_pairs(root, everything, include_training=True)
    assert ds.names == ("a", "b", "c") and "training pairs included" in note
    # another folder: every pair, read with the run's channel order and binning
    other = _dlmd_like(tmp_path / "e", ["x", "y"])
    ds, _ = evaluation_pairs(other, trained)
    assert ds.names == ("x", "y") and ds.image_shape == (3, 4, 7)
    # checkpoints that predate the record: every pair, as stored
    ds, _ = evaluation_pairs(root, {})
    assert len(ds) == 3 and ds.image_shape == (3, 18, 30)
    with pytest.raises(InvalidInputError, match="no pair named zz to evaluate"):
        PairsDataset(root, only=["zz"])


def test_match_downsample_uses_the_kernel_files_fit_factor():
    def model(shape, factor=None):
        return KernelModel(kernels=np.ones((1, 3, *shape), np.float32), basis="si",
                           sensor_shape=shape,
                           provenance={"downsample": factor} if factor else {})

    assert match_downsample((270, 480), model((270, 480))) == 1
    assert match_downsample((270, 480), model((67, 120), 4)) == 4
    assert match_downsample((270, 480), model((67, 120), 4), requested=4) == 4
    with pytest.raises(InvalidInputError, match="--downsample 4 matches it"):
        match_downsample((270, 480), model((67, 120)))          # no provenance: say which
    with pytest.raises(InvalidInputError, match=r"binned by 2: 135x240.*67x120"):
        match_downsample((270, 480), model((67, 120), 4), requested=2)
    with pytest.raises(InvalidInputError, match="fit the kernels on these images"):
        match_downsample((270, 480), model((50, 50)))


def test_train_psf_seed_is_the_psf_loaders_kernel(tmp_path):
    from ekdun.nets.builder import seed_kernel_model
    from psfkit.calibration.psf_image import load_psf_image
    from psfkit.io import write_image

    psf = np.zeros((3, 16, 16), np.float32)
    psf[:, 6:9, 7:10] = 1.0
    psf[2] *= 3                                                   # channel gains differ
    write_image(tmp_path / "p.npy", psf)
    seed = seed_kernel_model(str(tmp_path / "p.npy"))
    np.testing.assert_array_equal(seed.kernels[0], load_psf_image(str(tmp_path / "p.npy")))
    np.testing.assert_allclose(seed.kernels[0].sum(axis=(1, 2)), 1, rtol=1e-6)
