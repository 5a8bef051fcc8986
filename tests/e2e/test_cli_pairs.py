"""``psfkit fit-pairs`` and ``psfkit eval-model`` end to end, and their bad-input errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from psfkit.cli import main
from psfkit.cli.vocabulary import RETIRED
from psfkit.fitting.pairs.fit import predict
from psfkit.fitting.pairs.options import NEWTON_TOLERANCE
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels


@pytest.fixture(scope="module")
def eigen_pairs(tmp_path_factory: pytest.TempPathFactory, write_pairs
                ) -> tuple[Path, Path, KernelModel]:
    """Two pairs folders (fit / held out) measured through a known eigen-kernel camera."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(7)
    h, w = 16, 24
    base = rng.random((1, 3, h, w)) ** 6
    kernels = np.concatenate([base, base + 0.4 * rng.random((2, 3, h, w)) ** 6])
    kernels /= kernels[0].sum(axis=(-2, -1), keepdims=True)
    model = KernelModel(kernels=kernels.astype(np.float32), basis="paper", convention="sensor",
                        sensor_shape=(h, w), channels=("R", "G", "B"))
    x = np.stack([[gaussian_filter(c, 0.8) for c in im] for im in rng.random((8, 3, h, w))])
    x = x.astype(np.float32)
    y = predict(model, x)
    root = tmp_path_factory.mktemp("pairs")
    return (write_pairs(root / "fit", x[:6], y[:6]), write_pairs(root / "held", x[6:], y[6:]),
            model)


def test_fit_pairs_then_eval_model_on_unseen_pairs(eigen_pairs, tmp_path: Path, capsys) -> None:
    fit_dir, held_dir, _ = eigen_pairs
    results = {}
    for name in ("si", "ek"):
        out = tmp_path / f"{name}.npz"
        assert main(["fit-pairs", str(fit_dir), "--basis", name, "--out", str(out),
                     "--no-scale", "--tikhonov", "1e-8", "--difference", "0",
                     "--iterations", "300", "--quiet", "--convention", "sensor",
                     "--report", str(tmp_path / f"{name}.json")]) == 0
        model = load_kernels(out)
        assert model.basis == ("si" if name == "si" else "paper")
        assert model.convention == "sensor"
        assert model.provenance["source"] == "psfkit fit-pairs"
        report = json.loads((tmp_path / f"{name}.json").read_text())
        assert len(report["training_error"]) == 6
        errors = tmp_path / f"{name}-eval.json"
        assert main(["eval-model", str(out), str(held_dir), "--out", str(errors)]) == 0
        results[name] = json.loads(errors.read_text())
    assert set(results["ek"]["per_pair"]) == {"im0", "im1"}
    assert results["ek"]["mean_raw"] < 0.05
    assert results["ek"]["mean_raw"] < 0.3 * results["si"]["mean_raw"]
    printed = capsys.readouterr().out
    assert "mean" in printed and "im1" in printed


def test_fit_pairs_downsample_is_remembered_by_eval_model(eigen_pairs, tmp_path: Path,
                                                         capsys) -> None:
    fit_dir, held_dir, _ = eigen_pairs
    out = tmp_path / "si2.npz"
    assert main(["fit-pairs", str(fit_dir), "--out", str(out), "--downsample", "2",
                 "--iterations", "20", "--quiet"]) == 0
    assert load_kernels(out).sensor_shape == (8, 12)
    ek = tmp_path / "ek2.npz"
    assert main(["fit-pairs", str(fit_dir), "--basis", "ek", "--out", str(ek), "--downsample",
                 "2", "--iterations", "5", "--quiet"]) == 0
    assert load_kernels(ek).convention == "sensor"            # one default: Eq. 7
    assert main(["eval-model", str(out), str(held_dir)]) == 0
    # a model of the wrong size is refused, naming both sizes
    capsys.readouterr()
    assert main(["eval-model", str(out), str(held_dir), "--downsample", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "16x24" in err and "8x12" in err


def test_fit_pairs_writes_physical_kernels_unless_asked_otherwise(eigen_pairs, tmp_path: Path,
                                                                 capsys) -> None:
    """Default: non-negative kernels, with the constraints, energies and support fraction in
    the kernel file's provenance; --no-nonneg gives the old unconstrained fit (negative
    lobes); --support-mask is honoured; the retired --energy and --nonneg-solver are accepted,
    change nothing and say so in one note each (issue 44)."""
    fit_dir, _, _ = eigen_pairs
    common = ["--basis", "ek", "--convention", "sensor", "--iterations", "40", "--quiet"]
    default, free = tmp_path / "default.npz", tmp_path / "free.npz"
    assert main(["fit-pairs", str(fit_dir), "--out", str(default), *common]) == 0
    assert "0 negative pixels" in capsys.readouterr().out
    assert main(["fit-pairs", str(fit_dir), "--out", str(free), "--no-nonneg", *common]) == 0
    assert "unconstrained" in capsys.readouterr().out
    model, unconstrained = load_kernels(default), load_kernels(free)
    assert model.kernels.min() >= 0 and unconstrained.kernels.min() < 0
    physics = model.provenance["physics"]
    assert physics["constraints"] == {"nonneg": True, "support": "none"}
    assert physics["negative_pixels"] == 0 and physics["nonfinite_pixels"] == 0
    np.testing.assert_allclose(physics["energy"], model.kernels.sum(axis=(-2, -1)), rtol=1e-5)
    assert unconstrained.provenance["physics"]["negative_pixels"] > 0
    assert unconstrained.provenance["options"]["nonneg"] is False

    mask = np.zeros((16, 24), np.uint8)
    mask[3:13, 4:20] = 1
    np.save(tmp_path / "mask.npy", mask)
    masked, retired = tmp_path / "masked.npz", tmp_path / "retired.npz"
    # the weight given: no cross-validation in these two runs
    support = ["--support-mask", str(tmp_path / "mask.npy"), "--difference", "1"]
    assert main(["fit-pairs", str(fit_dir), "--out", str(masked), *support, *common]) == 0
    assert capsys.readouterr().err == ""
    model = load_kernels(masked)
    assert np.abs(model.kernels[..., mask == 0]).max() == 0 and model.kernels.min() >= 0
    physics = model.provenance["physics"]
    assert physics["constraints"] == {"nonneg": True, "support": "mask"}
    assert physics["support_fraction"] <= mask.mean()
    assert model.provenance["support_mask"].endswith("mask.npy")
    assert main(["fit-pairs", str(fit_dir), "--out", str(retired), *support, *common,
                 "--energy", "fit", "--nonneg-solver", "fista"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [RETIRED[("fit-pairs", "--energy")][1],
                   RETIRED[("fit-pairs", "--nonneg-solver")][1]]
    assert all("deprecated and ignored" in line and "migration.md" in line for line in err)
    assert np.array_equal(load_kernels(retired).kernels, model.kernels)
    # a retired flag's value is still checked, in one line, and nothing is written
    assert main(["fit-pairs", str(fit_dir), "--out", str(tmp_path / "bad.npz"), *common,
                 "--nonneg-solver", "pcg"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--nonneg-solver" in err[0]
    assert not (tmp_path / "bad.npz").exists()


def test_fit_pairs_newton_solver_converges_and_says_so(eigen_pairs, tmp_path: Path,
                                                       capsys) -> None:
    """The non-negative solve (projected Newton): kernels at a KKT residual below the fit's
    tolerance (NEWTON_TOLERANCE; printed with "converged", and in the report), inside a
    --support-mask; with --no-nonneg there is none: conjugate gradients, restricted to the
    support when there is one (an exact solve; issue 44: one solver per problem)."""
    fit_dir, _, _ = eigen_pairs
    common = ["--basis", "ek", "--convention", "sensor", "--quiet"]
    out = tmp_path / "newton.npz"
    mask = np.zeros((16, 24), np.uint8)
    mask[3:13, 4:20] = 1
    np.save(tmp_path / "mask.npy", mask)
    assert main(["fit-pairs", str(fit_dir), "--out", str(out), "--support-mask",
                 str(tmp_path / "mask.npy"), "--report", str(tmp_path / "r.json"),
                 *common]) == 0
    printed = capsys.readouterr().out
    assert "Newton steps, KKT residual" in printed and "(converged)" in printed
    model = load_kernels(out)
    assert model.kernels.min() >= 0 and np.abs(model.kernels[..., mask == 0]).max() == 0
    kkt = float(printed.split("KKT residual")[1].split()[0])
    assert kkt < NEWTON_TOLERANCE
    step = json.loads((tmp_path / "r.json").read_text())["solver"][-1]
    assert step["method"] == "projected-newton-cg" and step["converged"]
    assert step["kkt_residual"] == pytest.approx(kkt, rel=0.1)
    for name, extra in (("free", []), ("restricted", ["--support-mask",
                                                      str(tmp_path / "mask.npy")])):
        other = tmp_path / f"{name}.npz"
        assert main(["fit-pairs", str(fit_dir), "--out", str(other), *common, "--no-nonneg",
                     *extra, "--report", str(tmp_path / f"{name}.json")]) == 0
        assert "Newton" not in capsys.readouterr().out
        last = json.loads((tmp_path / f"{name}.json").read_text())["solver"][-1]
        assert last["method"] == "pcg-frequency-gram" and last["converged"]
        assert last.get("restricted_to_support", False) == bool(extra)
        kernels = load_kernels(other).kernels
        assert kernels.min() < 0                        # unconstrained: its negative lobes
        if extra:
            assert np.abs(kernels[..., mask == 0]).max() == 0


def test_bad_input_one_line_errors_and_nothing_written(eigen_pairs, tmp_path: Path,
                                                        capsys, write_pairs) -> None:
    fit_dir, _, model = eigen_pairs
    out = tmp_path / "k.npz"
    cases = [
        (["fit-pairs", str(tmp_path / "missing"), "--out", str(out)], "no such pairs folder"),
        (["fit-pairs", str(fit_dir), "--basis", "zernike", "--out", str(out)], "zernike"),
        (["fit-pairs", str(fit_dir), "--out", str(tmp_path / "k.txt")], ".npz"),
        (["fit-pairs", str(fit_dir), "--out", str(out), "--downsample", "0"], "downsample"),
        (["eval-model", str(tmp_path / "none.npz"), str(fit_dir)], "none.npz"),
    ]
    np.save(tmp_path / "small_mask.npy", np.ones((5, 5), np.uint8))
    cases.append((["fit-pairs", str(fit_dir), "--out", str(out), "--support-mask",
                   str(tmp_path / "small_mask.npy")], "5x5"))
    # an option that would do nothing is refused, naming it (issue 22)
    cases.append((["fit-pairs", str(fit_dir), "--out", str(out), "--support-threshold", "0.3"],
                  "--support-threshold"))
    cases.append((["fit-pairs", str(fit_dir), "--out", str(out), "--support", "none",
                   "--support-threshold", "0.3"], "--support-threshold"))
    unpaired = tmp_path / "unpaired"
    write_pairs(unpaired, np.zeros((1, 3, 16, 24), np.float32),
                 np.ones((1, 3, 16, 24), np.float32))
    np.save(unpaired / "scene" / "extra.npy", np.zeros((16, 24, 3), np.float32))
    cases.append((["fit-pairs", str(unpaired), "--out", str(out)], "extra"))
    wrong_version = tmp_path / "v9.npz"
    save_kernels(wrong_version, model)
    with np.load(wrong_version) as z:
        arrays = dict(z)
    meta = json.loads(str(arrays["metadata"]))
    meta["version"] = 9
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(wrong_version, **arrays)
    cases.append((["eval-model", str(wrong_version), str(fit_dir)], "version"))
    for argv, words in cases:
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and words in err, (argv, err)
        assert "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("convention", ["source", "sensor"])
def test_fit_pairs_defaults_give_back_the_kernels_of_eigen_kernel_pairs(
        tmp_path: Path, capsys, convention: str, write_pairs) -> None:
    """Issue 23 item 5, by the command: noise-free pairs of a known eigen-kernel model (bench
    scene statistics) → ``psfkit fit-pairs --basis ek`` with its defaults returns the kernels
    (difference NCC ≥ 0.99, base NCC ≥ 0.999; the earlier defaults gave 0.6–0.9)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "psfkit"))
    from test_pairs_solver import _metrics, bench_scenes, known_eigen_kernels

    model = KernelModel(kernels=known_eigen_kernels().astype(np.float32), basis="paper",
                        convention=convention, sensor_shape=(32, 32),
                        channels=("R", "G", "B"))
    x = bench_scenes(40).astype(np.float32)
    pairs = write_pairs(tmp_path / "pairs", x, predict(model, x))
    out = tmp_path / "fit.npz"
    assert main(["fit-pairs", str(pairs), "--basis", "ek", "--convention", convention,
                 "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    m = _metrics(load_kernels(out).kernels.astype(np.float64),
                 model.kernels.astype(np.float64))
    assert m["base"] >= 0.999 and m["v"] >= 0.99 and m["h"] >= 0.99, m
