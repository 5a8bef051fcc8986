"""research/unet_absorption.py at a tiny size: the SI and EK operator oracles of the
dataset, classical ADMM-TV with each, and EK-DUN trained with each oracle frozen."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
#: the study, run as ``python -m research.unet_absorption`` from the repository root
SCRIPT = ("-m", "research.unet_absorption")


def test_absorption_benchmark_freezes_the_oracles(tmp_path):
    from psfkit.forward.kernelfile import load_kernels

    out = tmp_path / "absorb"
    done = subprocess.run([sys.executable, *SCRIPT, "--out", str(out), "--sensor", "32",
                           "32", "--n-train", "8", "--n-test", "4", "--epochs", "1",
                           "--tune", "2", "--iterations", "20", "--device", "cpu"],
                          cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((out / "results.json").read_text())
    assert len(rows) == 1 and rows[0]["n_train"] == 8 and rows[0]["half_fov"] == 30.0
    row = rows[0]
    # the better physics helps the classical solver (measured 11.6 → 13.1 dB at 32²)
    assert row["classical"]["EK"]["psnr"] > row["classical"]["SI"]["psnr"] + 0.3
    assert {r["seed"] for r in row["learned"]["SI"]} == {0}
    data = out / "data-fov30-n8"
    # the benchmark adds only the dataset's own oracles to it (the SI oracle goes to OUT)
    assert not list((data / "oracle").glob("si_*"))
    si = load_kernels(out / "si_oracles" / data.name / "si_source.npz")
    ek = load_kernels(data / "oracle" / "paper_source.npz")
    assert si.basis == "si" and si.kernels.shape[0] == 1
    # the SI oracle is not one of the EK oracle's kernels: a different least squares
    assert np.linalg.norm(si.kernels[0] - ek.kernels[0]) > 1e-3 * np.linalg.norm(ek.kernels[0])
    for name, oracle in (("SI-base", np.repeat(si.kernels, 3, axis=0)),
                         ("EK-last-2", ek.kernels)):
        run = out / "runs" / f"fov30-n8-{name}-t0"
        learned = load_kernels(run / "kernels_learned.npz").kernels
        # frozen: training did not move the oracle kernels
        np.testing.assert_array_equal(learned, oracle)
    assert "| ±30° | 8 |" in done.stdout and "= SI corrected + EK shortfall" in done.stdout
    # the absorbed share splits exactly into the SI correction and the EK shortfall
    line = next(x for x in done.stdout.splitlines() if x.startswith("| ±30° | 8 |"))
    absorbed, split = line.strip(" |").split(" | ")[-2:]
    corrected, shortfall = (int(v.strip(" %")) for v in split.split("+"))
    assert abs(int(absorbed.strip("%")) - (corrected + shortfall)) <= 1, line

    # --data: the same dataset given by path, one physics, another seed, fewer pairs; the
    # classical scores come from the cache written by the first call (same inputs, settings)
    cached = json.loads((out / "classical" / f"{data.name}-SI.json").read_text())
    assert cached["score"] == row["classical"]["SI"]
    again = subprocess.run([sys.executable, *SCRIPT, "--out", str(out), "--data", str(data),
                            "--n-train", "4", "--physics", "EK", "--seeds", "1", "--epochs", "1",
                            "--tune", "2", "--iterations", "20", "--device", "cpu"],
                           cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    assert again.returncode == 0, again.stderr[-3000:]
    rows = json.loads((out / "results.json").read_text())
    assert rows[0]["n_train"] == 4 and set(rows[0]["learned"]) == {"EK"}
    assert rows[0]["classical"] == row["classical"]
    assert (out / "runs" / "fov30-n4-EK-last-2-t1" / "kernels_learned.npz").is_file()
    assert not (out / "runs" / "fov30-n4-SI-base-t1").exists()
    assert "| ±30° | 4 |" in again.stdout

    bad = subprocess.run([sys.executable, *SCRIPT, "--out", str(out), "--data",
                          str(tmp_path / "nowhere")], cwd=REPO, capture_output=True, text=True,
                         timeout=120, check=False)
    assert bad.returncode != 0 and "nowhere" in bad.stderr
    assert "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
