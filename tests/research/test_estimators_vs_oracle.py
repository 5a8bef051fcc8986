"""research/estimators_vs_oracle.py at a tiny size: the grid and pairs fits scored
against the dataset's oracles, with the non-negative operator oracle beside them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
#: the study, run as ``python -m research.estimators_vs_oracle`` from the repository root
SCRIPT = ("-m", "research.estimators_vs_oracle")

pytestmark = pytest.mark.e2e


def test_estimators_are_scored_against_every_oracle(tmp_path):
    from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench
    from psfkit.forward.kernelfile import load_kernels

    data = make_virtual_bench(tmp_path / "data", VirtualBenchSpec(
        sensor_shape=(32, 32), n_train=8, n_test=2, grid_shape=(3, 3)),
        progress=False)
    work, out = tmp_path / "work", tmp_path / "scores.json"
    done = subprocess.run([sys.executable, *SCRIPT, str(data), "--conventions", "source",
                           "--no-unconstrained", "--nonneg-oracle", "--work", str(work),
                           "--oracle-scenes", "32",
                           "--json", str(out), "--threads", "1"],
                          cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    records = json.loads(out.read_text())["records"]
    pairs = {(r["a"], r["b"]) for r in records}
    nn = "operator oracle, non-negative (source)"
    for a in ("grid fit (source)", "pairs fit (source)", nn):
        assert (a, "operator oracle (source)") in pairs
    assert ("pairs fit (source)", nn) in pairs and ("grid fit (source)", nn) in pairs
    for r in records:
        for k in ("v", "h"):
            assert -1 <= r["difference_ncc"][k] <= 1
    oracle = load_kernels(work / "nonneg_oracle_source_32.npz")
    assert oracle.kernels.min() >= 0
    assert oracle.provenance["kind"] == "operator, non-negative"
    assert oracle.provenance["projected"]["kkt_residual"] < 1e-9
    assert "non-negative oracle (source)" in json.loads(out.read_text())["times"]
    assert np.isfinite(oracle.kernels).all()
