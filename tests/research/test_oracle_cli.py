"""``python -m research.oracle`` (``ekdun oracle`` until issue 44): the oracles of an existing
virtual-bench dataset from the command line.

``--write-dataset`` writes the dataset's oracles into it (``make-dataset`` did until issue 44),
listed in its manifest, and the dataset is still reused; the unconstrained operator oracle
``--out`` computes is that file (same scenes, same solver); the non-negative one, warm-started
from it, is the library's solve from scratch; the PSF oracle is the library's; bad input is
one line and writes nothing.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ekdun.data.virtual_bench import VirtualBenchSpec, dataset_is_current, make_virtual_bench
from psfkit.forward.kernelfile import load_kernels
from research.oracle import main
from research.oracles import difference_nccs, operator_oracle, oracle_file, psf_oracle

pytestmark = pytest.mark.e2e

SPEC = VirtualBenchSpec(sensor_shape=(32, 32), n_train=4, n_test=2, grid_shape=(3, 3))


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A dataset and its oracles, written by ``--write-dataset`` (48 scenes)."""
    data = make_virtual_bench(tmp_path_factory.mktemp("oracle_cli") / "data", SPEC,
                              progress=False)
    assert main([str(data), "--write-dataset", "--oracle-scenes", "48", "--quiet"]) == 0
    return data


def _lines(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


def test_write_dataset_lists_the_oracles_and_keeps_the_dataset_current(bench, capsys):
    manifest = json.loads((bench / "manifest.json").read_text())
    for convention in ("source", "sensor"):
        for kind in ("operator", "psf"):
            path = oracle_file(bench, convention, kind)
            assert path is not None and path.parent == bench / "oracle"
            assert load_kernels(path).convention == convention
        assert manifest["oracle"]["files"][convention]["operator_record"]["n_scenes"] == 48
    assert dataset_is_current(bench, SPEC)              # make-dataset would reuse it
    # again, with the scenes the dataset's oracle has (the default): kept, nothing written
    stamp = (bench / "manifest.json").stat().st_mtime_ns
    assert main([str(bench), "--write-dataset"]) == 0
    (line,) = _lines(capsys)
    assert line == (f"oracles (paper, source and sensor): {bench / 'oracle'}; 48 scenes "
                    "(already there, kept)")
    assert (bench / "manifest.json").stat().st_mtime_ns == stamp


@pytest.mark.parametrize("argv, words", [
    (["--write-dataset", "--kind", "psf"], ["--write-dataset", "--kind"]),
    (["--write-dataset", "--out", "{tmp}/k.npz"], ["--write-dataset", "--out"]),
    (["--write-dataset", "--oracle-scenes", "-3"], ["--oracle-scenes"]),
])
def test_write_dataset_refuses_what_it_does_not_take(bench, tmp_path, capsys, argv, words):
    before = (bench / "manifest.json").read_bytes()
    assert main([str(bench), *[a.format(tmp=tmp_path) for a in argv]]) == 2
    err = _lines(capsys)
    assert len(err) == 1 and all(w in err[0] for w in words), err
    assert (bench / "manifest.json").read_bytes() == before and list(tmp_path.iterdir()) == []
    # not a dataset: one line, nothing written into the folder
    assert main([str(tmp_path), "--write-dataset"]) == 2
    err = _lines(capsys)
    assert len(err) == 1 and "not a virtual-bench dataset" in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_unconstrained_oracle_is_the_datasets_file(bench, tmp_path, capsys):
    out = tmp_path / "free.npz"
    assert main([str(bench), "--out", str(out), "--convention", "source",
                 "--no-nonneg", "--quiet"]) == 0
    assert "operator oracle (paper, source)" in _lines(capsys)[-1]
    got = load_kernels(out)
    written = load_kernels(bench / "oracle" / "paper_source.npz")
    assert (got.basis, got.convention, got.kernels.shape) == ("paper", "source", (3, 3, 32, 32))
    # the same scenes (by default those of the dataset's oracle) and solver: the same kernels,
    # to the CG tolerance (1e-7 relative residual); measured 0 (bitwise) on one machine
    error = np.linalg.norm(got.kernels - written.kernels) / np.linalg.norm(written.kernels)
    assert error < 1e-5, error
    assert got.provenance["n_scenes"] == 48 and got.provenance["converged"]


def test_nonneg_oracle_warm_started_is_the_solve_from_scratch(bench, tmp_path, capsys):
    out = tmp_path / "nn.npz"
    start = bench / "oracle" / "paper_source.npz"
    assert main([str(bench), "--out", str(out), "--convention", "source",
                 "--start", str(start), "--no-convergence-check", "--quiet"]) == 0
    line = _lines(capsys)[-1]
    assert "operator, non-negative oracle" in line and "KKT" in line, line
    got = load_kernels(out)
    assert got.kernels.min() >= 0
    assert got.provenance["kind"] == "operator, non-negative"
    assert got.provenance["warm_start"] is True
    assert got.provenance["projected"]["converged"]
    cold = operator_oracle(SPEC, "source", n_scenes=48, check_convergence=False, nonneg=True)
    assert cold.model.kernels.min() >= 0
    ncc = difference_nccs(got.kernels.astype(np.float64),
                          cold.model.kernels.astype(np.float64))
    assert min(ncc.values()) > 1 - 1e-6, ncc          # measured 1 - 3e-13
    # and it is not the unconstrained oracle (which has negative lobes on this bench)
    free = load_kernels(start).kernels
    assert free.min() < 0 and np.abs(got.kernels - free).max() > 1e-3 * np.abs(free).max()


def test_psf_oracle_is_the_librarys(bench, tmp_path):
    out = tmp_path / "psf.npz"
    assert main([str(bench), "--kind", "psf", "--out", str(out), "--quiet"]) == 0
    got = load_kernels(out)
    assert got.convention == "sensor"               # the vocabulary's default convention
    want = psf_oracle(SPEC, "sensor").model.kernels
    np.testing.assert_array_equal(got.kernels, want)


@pytest.mark.parametrize("argv, words", [
    (["--out", "{tmp}/k.npy"], ["k.npy", ".npz"]),
    (["--out", "{tmp}/k.npz", "--kind", "psf", "--start", "{start}"], ["--start", "--kind"]),
    (["--out", "{tmp}/k.npz", "--basis", "zernike"], ["zernike"]),
    (["--out", "{tmp}/k.npz", "--start", "{start}"], ["--start", "paper/sensor", "source"]),
])
def test_bad_input_is_one_line_and_writes_nothing(bench, tmp_path, capsys, argv, words):
    start = bench / "oracle" / "paper_source.npz"
    args = [a.format(tmp=tmp_path, start=start) for a in argv]
    assert main([str(bench), *args, "--quiet"]) != 0
    err = _lines(capsys)
    assert len(err) == 1 and all(w in err[0] for w in words), err
    assert list(tmp_path.iterdir()) == []


def test_not_a_dataset_and_existing_output(bench, tmp_path, capsys):
    assert main([str(tmp_path), "--out", str(tmp_path / "k.npz")]) != 0
    err = _lines(capsys)
    assert len(err) == 1 and "not a virtual-bench dataset" in err[0], err
    existing = tmp_path / "k.npz"
    existing.write_bytes(b"keep")
    before = (bench / "manifest.json").read_bytes()
    assert main([str(bench), "--kind", "psf", "--out", str(existing)]) != 0
    err = _lines(capsys)
    assert len(err) == 1 and "k.npz" in err[0], err
    assert existing.read_bytes() == b"keep"
    assert (bench / "manifest.json").read_bytes() == before   # the dataset is left as it was
