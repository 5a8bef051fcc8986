"""research/consistency_descent.py at 32²: the kernels alone descend the measurement-
consistency term; its numbers are those of an independent path (psfkit's predict and scaled
errors in float64), both optimisers descend, Adam runs at training's kernel learning rate,
and bad input is one line with nothing written."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench
from psfkit.fitting.pairs.fit import predict, relative_errors
from psfkit.forward.kernelfile import load_kernels, save_kernels
from psfkit.io import read_pairs
from research.oracles import write_dataset_oracles

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
#: the study, run as ``python -m research.consistency_descent`` from the repository root
SCRIPT = ("-m", "research.consistency_descent")
SPEC = VirtualBenchSpec(sensor_shape=(32, 32), n_train=8, n_test=2, grid_shape=(3, 3))


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("descent")
    data = make_virtual_bench(root / "data", SPEC, progress=False)
    write_dataset_oracles(data, n_scenes=48)
    oracle = load_kernels(data / "oracle" / "paper_source.npz")
    seed = root / "one_psf.npz"       # Kv = Kh = Kbase of the oracle: the one-PSF start
    save_kernels(seed, replace(oracle, kernels=np.repeat(oracle.kernels[:1], 3, axis=0)))
    return data, seed


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *SCRIPT, *args], cwd=REPO, capture_output=True,
                          text=True, timeout=600, check=False)


def test_descent_scores_against_the_oracle_and_descends(bench, tmp_path):
    data, seed = bench
    out = tmp_path / "out"
    done = _run("--data", str(data), "--seed", str(seed), "--out", str(out),
                "--optimisers", "adam,lbfgs", "--kernel-lr-scales", "0.01,0.1",
                "--report-at", "1,10", "--reference", f"copy={seed}")
    assert done.returncode == 0, done.stderr[-3000:]
    doc = json.loads((out / "results.json").read_text())
    refs = {r["reference"]: r for r in doc["references"]}
    assert set(refs) == {"seed", "the oracle itself", "copy"}
    itself = refs["the oracle itself"]
    assert itself["oracle_v_diff_ncc"] == pytest.approx(1.0, abs=1e-9)
    assert itself["oracle_h_disp_corr"] == pytest.approx(1.0, abs=1e-9)
    assert refs["seed"]["oracle_v_diff_ncc"] is None        # one PSF: no difference kernels
    assert refs["copy"]["train_consistency"] == refs["seed"]["train_consistency"]

    # L_phys of a kernel file = the mean squared scaled relative error of psfkit's predict
    oracle = load_kernels(data / "oracle" / "paper_source.npz")
    for split in ("train", "test"):
        scenes, measurements = read_pairs(data / split).load_all()
        for name, model in (("the oracle itself", oracle), ("seed", load_kernels(seed))):
            errors = relative_errors(predict(model, scenes), measurements)["scaled"]
            assert refs[name][f"{split}_consistency"] == pytest.approx(
                float(np.mean(errors**2)), rel=1e-4)
    # the oracle is the better forward model of the two (the check has a direction)
    assert itself["train_consistency"] < 0.75 * refs["seed"]["train_consistency"]

    runs = doc["runs"]
    assert [(r["optimiser"], r.get("kernel_lr_scale")) for r in runs] == [
        ("adam", 0.01), ("adam", 0.1), ("lbfgs", None)]
    # Adam's kernel learning rate is training's: network lr × kernel_lr_scale × 1 (free)
    assert runs[0]["kernel_lr"] == pytest.approx(2e-3 * 0.01)
    assert [r["passes"] for r in runs[0]["trajectory"]] == [1, 10]
    for run in runs:
        first, last = run["trajectory"][0], run["trajectory"][-1]
        assert last["passes"] >= 10
        assert last["train_consistency"] < refs["seed"]["train_consistency"], run["optimiser"]
        assert last["train_consistency"] <= first["train_consistency"] * 1.001
        assert last["oracle_v_diff_ncc"] is not None and -1 <= last["oracle_v_diff_ncc"] <= 1
    assert "| lbfgs |" in done.stdout and "| the oracle itself |" in done.stdout


def test_bad_input_is_one_line_and_writes_nothing(bench, tmp_path):
    data, seed = bench
    no_oracle = tmp_path / "no_oracle"
    (no_oracle / "train").mkdir(parents=True)
    for args, words in [
        (("--data", str(no_oracle), "--seed", str(seed)), "no operator oracle"),
        (("--data", str(data), "--seed", str(seed), "--optimisers", "sgd"), "unknown sgd"),
        (("--data", str(data), "--seed", str(seed), "--report-at", "0"), "--report-at"),
        (("--data", str(data), "--seed", str(tmp_path / "missing.npz")), "missing.npz"),
    ]:
        out = tmp_path / "out"
        done = _run(*args, "--out", str(out))
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1, done.stderr
        assert lines[0].startswith("bench_consistency_descent: error:") and words in lines[0]
        assert not out.exists()
