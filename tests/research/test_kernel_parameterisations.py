"""research/kernel_parameterisations.py (the Fig. 7 experiment) at a tiny size: the
dataset made from the command line, runs per λ, every run and the seeds scored against the
dataset's operator oracle, results merged across invocations on λ, and a dataset without
oracle."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
#: the study, run as ``python -m research.kernel_parameterisations`` from the repository root
SCRIPT = ("-m", "research.kernel_parameterisations")
ORACLE_KEYS = ("oracle_v_diff_ncc", "oracle_h_diff_ncc", "oracle_v_disp_corr",
               "oracle_h_disp_corr", "oracle_v_epe_px", "oracle_h_epe_px", "oracle_angles")


def _bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *SCRIPT, *args, "--epochs", "1",
                           "--threads", "1", "--device", "cpu"],
                          cwd=REPO, capture_output=True, text=True, timeout=600, check=False)


def test_benchmark_scores_every_run_against_the_oracle(tmp_path):
    from psfkit.cli import main as psfkit_main
    from psfkit.fitting.pairs.fit import predict, relative_errors
    from psfkit.forward.kernelfile import load_kernels
    from psfkit.io import read_pairs
    from research.compare import compare_kernels

    out = tmp_path / "kp"
    done = _bench("--out", str(out), "--sensor", "32", "32", "--n-train", "8", "--n-test", "2",
                  "--params", "free,physical", "--physics-weights", "0,1", "--batch-size", "4")
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads((out / "results.json").read_text())
    assert doc["spec"]["sensor_shape"] == [32, 32] and doc["spec"]["n_train"] == 8
    convention = load_kernels(out / "kernels_fit.npz").convention
    oracle = out / "dataset" / "oracle" / f"paper_{convention}.npz"
    assert doc["oracle"] == {"file": str(oracle), "kind": "operator", "convention": convention}

    runs = doc["runs"]
    assert len(runs) == 8        # 2 seeds x 2 parameterisations x 2 physics weights
    assert sorted({r["physics_weight"] for r in runs}) == [0.0, 1.0]
    for r in runs:
        assert f"-l{r['physics_weight']:g}-" in Path(r["run"]).name
        assert all(k in r for k in ORACLE_KEYS), sorted(r)
        assert -1 <= r["oracle_v_diff_ncc"] <= 1 and np.isfinite(r["psnr"])
        # λ reached the training: only λ > 0 logs the measurement-consistency term
        assert (r["final_physics_loss"] is None) == (r["physics_weight"] == 0), r["run"]
        meta = json.loads((Path(r["run"]) / "numbers.json").read_text())
        assert meta["physics_weight"] == r["physics_weight"]
    # a run's oracle numbers are its learned kernels against the oracle (the reference)
    row = next(r for r in runs if r["seed"] == "measured" and r["param"] == "free"
               and r["physics_weight"] == 1.0)
    expected = compare_kernels(Path(row["run"]) / "kernels_learned.npz", oracle).learned
    assert row["oracle_v_diff_ncc"] == pytest.approx(expected.numbers()["v_diff_ncc"], abs=1e-9)
    assert row["oracle_h_epe_px"] == pytest.approx(expected.numbers()["h_epe_px"], abs=1e-9)

    refs = {r["reference"]: r for r in doc["references"]}
    assert set(refs) == {"measured fit (seed)", "one PSF (seed)", "the oracle itself"}
    itself = refs["the oracle itself"]
    assert itself["oracle_v_diff_ncc"] == pytest.approx(1.0, abs=1e-9)
    assert itself["oracle_h_diff_ncc"] == pytest.approx(1.0, abs=1e-9)
    assert itself["oracle_v_disp_corr"] == pytest.approx(1.0, abs=1e-9)
    assert itself["oracle_v_epe_px"] == pytest.approx(0.0, abs=1e-9)
    assert max(itself["oracle_angles"]) < 1e-6
    fit = compare_kernels(out / "kernels_fit.npz", oracle).learned.numbers()
    assert refs["measured fit (seed)"]["oracle_v_diff_ncc"] == pytest.approx(fit["v_diff_ncc"])
    assert refs["measured fit (seed)"]["oracle_v_diff_ncc"] < 0.999   # not the oracle itself
    # one PSF: no difference kernels, so no difference NCC (null, never a number)
    assert refs["one PSF (seed)"]["oracle_v_diff_ncc"] is None
    # prediction errors on the test pairs: what psfkit eval-model gives for the same file,
    # and the oracle (the best eigen-kernel model of the simulator) predicts better than the
    # shift-invariant one-PSF seed
    scenes, measurements = read_pairs(out / "dataset" / "test").load_all()
    learned = load_kernels(Path(row["run"]) / "kernels_learned.npz")
    expected_error = relative_errors(predict(learned, scenes), measurements)["scaled"].mean()
    assert row["test_prediction_error"] == pytest.approx(expected_error, rel=1e-9)
    assert all(0 < r["test_prediction_error"] < 1 for r in runs)
    assert (itself["test_prediction_error"]
            < refs["one PSF (seed)"]["test_prediction_error"]), refs

    table = done.stdout
    assert "| λ |" in table and "oracle: diff. NCC Kv / Kh" in table
    assert "| the oracle itself | 1.000 / 1.000 | +1.00 / +1.00 | 0.000 / 0.000 |" in table
    assert "paired ΔPSNR to free pixels, measured / physical, λ = 1:" in table

    # a second invocation on the same folder: another training seed of λ = 1 only; the
    # earlier runs are kept (merged on λ too), the new one is added, the spread is reported
    again = _bench("--out", str(out), "--params", "free", "--seeds", "one-psf",
                   "--physics-weights", "1", "--train-seeds", "1", "--batch-size", "4")
    assert again.returncode == 0, again.stderr[-3000:]
    runs = json.loads((out / "results.json").read_text())["runs"]
    assert len(runs) == 9
    assert sum(r["seed"] == "one-psf" and r["param"] == "free" and r["physics_weight"] == 1
               for r in runs) == 2
    assert "one-psf / free, λ = 1, 2 training seeds: PSNR" in again.stdout
    assert "vs oracle: diff. NCC" in again.stdout
    # --table re-renders the same table from results.json alone
    table = _bench("--out", str(out), "--table")
    assert table.returncode == 0 and table.stdout.strip() in again.stdout

    # the pairs seed: psfkit fit-pairs of the training pairs (the same kernels as the
    # command line gives), trained from and scored against the oracle as a reference row
    pairs = _bench("--out", str(out), "--params", "free", "--seeds", "pairs",
                   "--batch-size", "4")
    assert pairs.returncode == 0, pairs.stderr[-3000:]
    seed = out / "kernels_pairs.npz"
    cli = tmp_path / "pairs_cli.npz"
    assert psfkit_main(["fit-pairs", str(out / "dataset" / "train"), "--basis", "paper",
                        "--convention", convention, "--quiet", "--out", str(cli)]) == 0
    k_seed, k_cli = load_kernels(seed).kernels, load_kernels(cli).kernels
    np.testing.assert_allclose(k_seed, k_cli, atol=1e-6 * np.abs(k_cli).max())
    assert load_kernels(seed).convention == convention
    for key in ("options", "physics", "training_error"):     # as the command line records
        assert load_kernels(seed).provenance[key] == load_kernels(cli).provenance[key], key
    doc = json.loads((out / "results.json").read_text())
    (row,) = [r for r in doc["runs"] if r["seed"] == "pairs"]
    assert Path(row["run"]).name.startswith("pairs-free-last-2-l0-")
    refs = {r["reference"]: r for r in doc["references"]}
    ours = compare_kernels(seed, oracle).learned.numbers()
    assert refs["pairs fit (seed)"]["oracle_v_diff_ncc"] == pytest.approx(ours["v_diff_ncc"])
    assert refs["pairs fit (seed)"]["oracle_h_disp_corr"] == pytest.approx(
        ours["h_disp_corr"])
    assert "| pairs fit (seed) |" in pairs.stdout and "| pairs | free |" in pairs.stdout
    assert len(doc["runs"]) == 10

    # the unconstrained pairs seed: fit-pairs --no-nonneg, beside the non-negative one
    free = _bench("--out", str(out), "--params", "free", "--seeds", "pairs-free",
                  "--batch-size", "4")
    assert free.returncode == 0, free.stderr[-3000:]
    cli_free = tmp_path / "pairs_free_cli.npz"
    assert psfkit_main(["fit-pairs", str(out / "dataset" / "train"), "--basis", "paper",
                        "--convention", convention, "--no-nonneg", "--quiet",
                        "--out", str(cli_free)]) == 0
    k_free = load_kernels(out / "kernels_pairs_free.npz").kernels
    k_cli_free = load_kernels(cli_free).kernels
    np.testing.assert_allclose(k_free, k_cli_free, atol=1e-6 * np.abs(k_cli_free).max())
    assert k_free.min() < 0 <= k_seed.min()       # unconstrained vs non-negative
    doc = json.loads((out / "results.json").read_text())
    assert {r["seed"] for r in doc["runs"]} >= {"pairs", "pairs-free"}
    assert {"pairs fit (seed)", "unconstrained pairs fit (seed)"} <= {
        r["reference"] for r in doc["references"]}
    assert len(doc["runs"]) == 11

    # the oracle as the seed: the run starts from the oracle's kernels exactly, is scored
    # against it like every run, and adds no reference row (that is "the oracle itself")
    start = _bench("--out", str(out), "--params", "free", "--seeds", "oracle",
                   "--batch-size", "4")
    assert start.returncode == 0, start.stderr[-3000:]
    doc = json.loads((out / "results.json").read_text())
    (row,) = [r for r in doc["runs"] if r["seed"] == "oracle"]
    assert Path(row["run"]).name.startswith("oracle-free-last-2-l0-")
    np.testing.assert_array_equal(
        load_kernels(Path(row["run"]) / "kernels_initial.npz").kernels,
        load_kernels(oracle).kernels.astype(np.float32))
    assert -1 <= row["oracle_v_diff_ncc"] <= 1
    assert sum(r["reference"] == "the oracle itself" for r in doc["references"]) == 1
    assert len(doc["references"]) == 5 and len(doc["runs"]) == 12

    # a run folder trained with other settings is refused before anything is trained
    refused = _bench("--out", str(out), "--params", "free", "--seeds", "one-psf",
                     "--physics-weights", "1", "--train-seeds", "1", "--lr", "1e-3")
    assert refused.returncode == 2
    assert len(refused.stderr.strip().splitlines()) == 1 and "trained with lr" in refused.stderr
    # a dataset option that disagrees with the folder's dataset is refused
    refused = _bench("--out", str(out), "--sensor", "64", "64")
    assert refused.returncode == 2 and "made with --sensor 32 32, not 64 64" in refused.stderr


def test_benchmark_without_oracle_reports_measured_columns(tmp_path):
    from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench

    data = make_virtual_bench(tmp_path / "data", VirtualBenchSpec(
        sensor_shape=(32, 32), n_train=4, n_test=1, grid_shape=(3, 3)),
        progress=False)
    out = tmp_path / "kp"
    done = _bench("--out", str(out), "--data", str(data), "--params", "free", "--seeds",
                  "one-psf", "--batch-size", "4")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "No oracle:" in done.stdout and "--write-dataset" in done.stdout
    assert "oracle: diff. NCC" not in done.stdout and "| λ |" in done.stdout
    doc = json.loads((out / "results.json").read_text())
    assert doc["oracle"] is None and doc["references"] == []
    (row,) = doc["runs"]
    assert row["physics_weight"] == 0.0 and not any(k.startswith("oracle_") for k in row)
    # no oracle to start from: refused in one line
    refused = _bench("--out", str(out), "--data", str(data), "--params", "free", "--seeds",
                     "oracle", "--batch-size", "4")
    assert refused.returncode == 2, refused.stderr[-3000:]
    assert len(refused.stderr.strip().splitlines()) == 1 and "--seeds oracle" in refused.stderr


def test_results_file_gets_each_run_at_once(tmp_path):
    """``record`` merges one finished run into results.json: a run of the same set-up and
    training seed replaces its earlier row, every other row stays (an interrupted invocation
    keeps the runs it finished; earlier invocations' runs are kept)."""
    from research.kernel_parameterisations import record

    path = tmp_path / "results.json"
    header = {"dataset": "d", "spec": {}, "oracle": None, "oracle_note": "n", "references": []}

    def row(seed: str, train_seed: int, psnr: float) -> dict:
        return {"seed": seed, "param": "free", "schedule": "last-2", "preset": "tiny",
                "physics_weight": 0.0, "train_seed": train_seed, "epochs": 15, "psnr": psnr,
                "compare": {"large": "not kept"}}

    record(path, header, row("measured", 0, 20.0))
    record(path, header, row("one-psf", 0, 21.0))
    record(path, header, row("measured", 0, 22.0))          # the same run, scored again
    doc = json.loads(path.read_text())
    assert doc["oracle_note"] == "n"
    assert sorted((r["seed"], r["psnr"]) for r in doc["runs"]) == [("measured", 22.0),
                                                                  ("one-psf", 21.0)]
    assert all("compare" not in r for r in doc["runs"])


def _record_many(path: str, seed: str, count: int, start) -> None:
    from research.kernel_parameterisations import record

    start.wait()                        # both processes imported: their writes overlap
    header = {"dataset": "d", "spec": {}, "oracle": None, "oracle_note": "n", "references": []}
    for i in range(count):
        record(Path(path), header, {"seed": seed, "param": "free", "schedule": "last-2",
                                    "preset": "tiny", "physics_weight": 0.0, "train_seed": i,
                                    "epochs": 15, "psnr": float(i)})


def test_invocations_at_once_on_one_folder_keep_each_others_runs(tmp_path):
    """Two invocations on one OUT (two CPU lanes) record runs at the same time: the lock
    around the read-merge-write keeps every row (without it, one overwrites the other's)."""
    import multiprocessing

    path = tmp_path / "results.json"
    ctx = multiprocessing.get_context("spawn")
    start = ctx.Barrier(2)
    procs = [ctx.Process(target=_record_many, args=(str(path), seed, 40, start))
             for seed in ("measured", "one-psf")]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=300)
        assert p.exitcode == 0
    runs = json.loads(path.read_text())["runs"]
    assert len(runs) == 80
    assert {(r["seed"], r["train_seed"]) for r in runs} == {
        (s, i) for s in ("measured", "one-psf") for i in range(40)}
