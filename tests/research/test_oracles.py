"""The eigen-kernel oracles of the virtual bench (issue 23 item 1): an operator that is itself
an eigen-kernel model is its own oracle; a shift-invariant bench's oracle is that PSF for every
kernel; ``write_dataset_oracles`` writes both oracles into a dataset, loadable, recorded in its
manifest, and the dataset is still reused by make-dataset."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from ekdun.data.bench_spec import dense_model_for
from ekdun.data.dense_model import DenseShiftVariantModel
from ekdun.data.virtual_bench import VirtualBenchSpec, dataset_is_current, make_virtual_bench
from psfkit.fitting.pairs.batches import PairBatches
from psfkit.fitting.pairs.fit import predict
from psfkit.fitting.pairs.solver import solve_kernels
from psfkit.forward.convolution import eigen_kernel_forward, kernel_spectra
from psfkit.forward.geometry import padded_shape
from psfkit.forward.kernelfile import KernelModel, load_kernels
from research.oracles import (
    dense_psf_oracle,
    difference_nccs,
    operator_oracle,
    oracle_file,
    oracle_scenes,
    psf_oracle,
    white_scenes,
    write_dataset_oracles,
)
from research.synthetic import caustic_psf

SPEC = VirtualBenchSpec(sensor_shape=(32, 32), n_train=8, n_test=2, grid_shape=(3, 3))


def _eigen_model(convention: str) -> KernelModel:
    base = caustic_psf((32, 32), 3, seed=1).astype(np.float64)
    kernels = np.stack([base, 0.9 * np.roll(base, 2, axis=1), 0.9 * np.roll(base, 2, axis=2)])
    return KernelModel(kernels=kernels.astype(np.float32), basis="paper",
                       convention=convention, sensor_shape=(32, 32))


def test_an_eigen_kernel_operator_is_its_own_oracle():
    for convention in ("source", "sensor"):
        truth = _eigen_model(convention)
        result = operator_oracle(SPEC, convention, n_scenes=48,
                                 forward=lambda x, m=truth: torch.as_tensor(
                                     predict(m, x.numpy(), dtype=torch.float64)))
        got = result.model.kernels.astype(np.float64)
        ncc = difference_nccs(got, truth.kernels.astype(np.float64))
        assert ncc["base"] > 0.9999 and ncc["v"] > 0.999 and ncc["h"] > 0.999, ncc
        rec = result.record
        assert rec["converged"] and rec["relative_residual"] < 1e-6
        assert rec["relative_prediction_error"] < 1e-4
        assert rec["convergence"]["v_difference_ncc"] > 0.999


def test_a_nonnegative_eigen_kernel_operator_is_its_own_nonnegative_oracle():
    truth = _eigen_model("source")
    assert truth.kernels.min() >= 0
    result = operator_oracle(SPEC, "source", n_scenes=48, check_convergence=False,
                             nonneg=True,
                             forward=lambda x: torch.as_tensor(
                                 predict(truth, x.numpy(), dtype=torch.float64)))
    got = result.model.kernels.astype(np.float64)
    assert got.min() >= 0
    ncc = difference_nccs(got, truth.kernels.astype(np.float64))
    assert ncc["base"] > 0.9999 and ncc["v"] > 0.999 and ncc["h"] > 0.999, ncc
    assert result.record["kind"] == "operator, non-negative"
    assert result.record["projected"]["kkt_residual"] < 1e-9


def test_nonnegative_operator_oracle_is_the_best_nonnegative_model():
    """On the bench (whose unconstrained oracle has negative lobes), the non-negative oracle
    is feasible, predicts the dense model worse than the unconstrained oracle (a constraint)
    but better than that oracle clipped to >= 0 (it re-fits, not clips), and its projected
    Newton solve meets the optimality (KKT) conditions of the non-negative least squares,
    checked directly on the normal equations built here: the gradient vanishes where the
    kernels are positive and points outwards where they are 0."""
    n = 32
    free = operator_oracle(SPEC, "source", n_scenes=n, check_convergence=False)
    nn = operator_oracle(SPEC, "source", n_scenes=n, check_convergence=False, nonneg=True)
    k_free = free.model.kernels.astype(np.float64)
    negative = np.clip(-k_free[1:], 0, None).sum() / np.abs(k_free[1:]).sum()
    assert negative > 0.03, negative               # measured 0.07: there is something to fix
    scenes = oracle_scenes(SPEC, n)
    with torch.no_grad():
        clean = dense_model_for(SPEC)(torch.as_tensor(scenes, dtype=torch.float64))

    def loss(kernels: np.ndarray) -> float:
        model = KernelModel(kernels=kernels.astype(np.float32), basis="paper",
                            convention="source", sensor_shape=(32, 32))
        return float(((predict(model, scenes, dtype=torch.float64) - clean.numpy()) ** 2).sum())

    k_nn = nn.model.kernels.astype(np.float64)
    assert k_nn.min() >= 0
    # measured: free 1.00, non-negative 1.32, clipped 30 (relative to free)
    assert loss(k_free) < loss(k_nn) < 0.85 * loss(np.clip(k_free, 0, None))
    projected = nn.record["projected"]
    assert projected["method"] == "projected-newton-cg" and projected["kkt_residual"] < 1e-9
    # the optimality conditions, on the normal equations of the same problem built here
    # (the oracle's kernels are stored in float32: conditions to that rounding)
    batches = PairBatches(scenes, "paper", "source", (32, 32))
    _start, _, system = solve_kernels(batches, clean, max_iterations=0)
    k = torch.as_tensor(k_nn)
    gradient = system["normal"](k) - system["rhs"]
    scale = float(gradient.abs().max()) + float(system["rhs"].abs().max())
    positive = k > 1e-6 * float(k.max())
    assert float(gradient[positive].abs().max()) < 1e-4 * scale
    assert float(gradient[~positive].min()) > -1e-4 * scale


def test_shift_invariant_bench_oracles_are_its_psf():
    """A dense model whose nodes all carry one PSF is the SI model: both oracles give that
    PSF for Kbase, Kv and Kh, in both conventions."""
    psf = caustic_psf((32, 32), 3, seed=2).astype(np.float64)
    nodes = np.broadcast_to(psf, (3, 3, *psf.shape)).copy()
    dense = DenseShiftVariantModel(nodes, np.array([0.0, 16.0, 31.0]),
                                   np.array([0.0, 16.0, 31.0]), (32, 32), "source")
    grid = padded_shape((32, 32))
    x = torch.rand(2, 3, 32, 32, dtype=torch.float64)
    si = eigen_kernel_forward(x, kernel_spectra(torch.as_tensor(psf)[None], grid), None, grid)
    assert torch.allclose(dense(x), si, rtol=0, atol=1e-12 * float(si.abs().max()))
    for convention in ("source", "sensor"):
        result = operator_oracle(SPEC, convention, n_scenes=32, forward=dense,
                                 check_convergence=False)
        got = result.model.kernels.astype(np.float64)
        error = np.linalg.norm(got - psf[None]) / np.linalg.norm(np.broadcast_to(psf, got.shape))
        assert error < 5e-3, (convention, error)     # measured 7e-4 (32 scenes)


def test_psf_oracle_of_a_bench_fits_its_node_psfs():
    for convention in ("source", "sensor"):
        result = psf_oracle(SPEC, convention)
        k = result.model.kernels
        assert k.shape == (3, 3, 32, 32) and np.isfinite(k).all()
        assert result.record["nodes"] == [3, 3]
        # a real correction: Kv and Kh differ from Kbase
        assert np.linalg.norm(k[1] - k[0]) > 0.01 * np.linalg.norm(k[0])


def test_white_scene_operator_oracle_is_the_cropped_dense_psf_fit():
    """Two independent solvers of one least squares: for scenes of independent zero-mean
    pixels, E‖crop((A_dense − A_K) x)‖² is the per-pixel fit of every scene point's
    interpolated PSF on the part that lands on the sensor (``dense_psf_oracle(crop=True)``).
    The frequency-domain pairs solver over random white scenes converges to the closed-form
    per-pixel fit (error ∝ 1/n); the dataset's natural scenes give a different model."""
    crop = dense_psf_oracle(SPEC, "source", crop=True).model.kernels.astype(np.float64)
    full = dense_psf_oracle(SPEC, "source", crop=False).model.kernels.astype(np.float64)

    def white(n: int) -> np.ndarray:
        return operator_oracle(SPEC, "source", scenes=white_scenes(SPEC, n),
                               check_convergence=False).model.kernels.astype(np.float64)

    fits = {n: white(n) for n in (32, 96)}
    gap = {n: 1 - min(difference_nccs(k, crop).values()) for n, k in fits.items()}
    # measured 2.2e-3 (32 scenes) and 7.1e-4 (96): the Monte-Carlo error of 1/n
    assert gap[96] < 1.5e-3 and gap[96] < 0.6 * gap[32], gap
    # the crop is part of the identity: the uncropped fit is farther (measured 1.9e-3)
    assert 1 - min(difference_nccs(fits[96], full).values()) > 1.5 * gap[96]
    natural = operator_oracle(SPEC, "source", n_scenes=96,
                              check_convergence=False).model.kernels.astype(np.float64)
    # the scene spectrum is what separates the oracles (measured 2.3e-2, 30x the white gap)
    assert 1 - min(difference_nccs(natural, crop).values()) > 10 * gap[96]


def test_write_dataset_oracles_lists_them_and_the_dataset_is_still_reused(tmp_path):
    spec = VirtualBenchSpec(sensor_shape=(32, 32), n_train=4, n_test=2, grid_shape=(3, 3))
    root = make_virtual_bench(tmp_path / "data", spec, progress=False)
    # make-dataset writes no oracles any more
    assert not (root / "oracle").exists() and oracle_file(root, "source") is None
    assert "oracle" not in json.loads((root / "manifest.json").read_text())
    record, computed = write_dataset_oracles(root, n_scenes=48)
    assert computed
    manifest = json.loads((root / "manifest.json").read_text())
    oracle = manifest["oracle"]
    assert oracle == json.loads(json.dumps(record))
    for convention in ("source", "sensor"):
        entry = oracle["files"][convention]
        for kind in ("operator", "psf"):
            name = entry[kind]
            assert f"oracle/{name}" in manifest["files"]
            model = load_kernels(root / "oracle" / name)
            assert model.convention == convention and model.basis == "paper"
            assert model.kernels.shape == (3, 3, 32, 32)
        rec = entry["operator_record"]
        assert rec["n_scenes"] == 48 and rec["relative_residual"] < 1e-6
        assert set(entry["psf_vs_operator"]["difference_ncc"]) == {"base", "v", "h"}
        # the operator oracle predicts the dense model at least as well as the PSF oracle
        pred = entry["psf_vs_operator"]["prediction_error"]
        assert pred["operator"] <= pred["psf"] * 1.05
    # the manifest's file list and hash cover the oracles: make-dataset of the same spec
    # reuses the dataset (its oracles included) instead of rebuilding it
    assert dataset_is_current(root, spec)
    stamp = (root / "manifest.json").stat().st_mtime_ns
    assert make_virtual_bench(root, spec, progress=False) == root
    assert (root / "manifest.json").stat().st_mtime_ns == stamp
    assert (root / "oracle" / "paper_source.npz").is_file()
    # the same oracles again: kept, nothing written; other scenes: computed anew
    assert write_dataset_oracles(root, n_scenes=48)[1] is False
    assert (root / "manifest.json").stat().st_mtime_ns == stamp
    # oracle_file: the file the manifest lists, None without oracles or outside a dataset
    off = make_virtual_bench(tmp_path / "off", replace(spec, n_train=2, n_test=1),
                             progress=False)
    assert oracle_file(root, "sensor") == root / "oracle" / oracle["files"]["sensor"]["operator"]
    assert oracle_file(root, "source", "psf") == root / "oracle" / "psf_paper_source.npz"
    assert oracle_file(off, "source") is None and oracle_file(tmp_path, "source") is None
    with pytest.raises(ValueError, match="kind"):
        oracle_file(root, "source", "grid")
