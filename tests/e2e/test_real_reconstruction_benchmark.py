"""``benchmarks/bench_real_reconstruction.py`` runs its leave-one-out protocol on the DLMD pairs
and chooses iterations on the fit pairs (tiny sizes; the numbers are measurements, see
research/notes/reconstruction-studies.md)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_benchmark_reports_both_models_with_iterations_chosen_from_the_grid(real_data,
                                                                            tmp_path):
    pairs = real_data("dlmd_mirflickr")
    out = tmp_path / "rows.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "benchmarks/bench_real_reconstruction.py", "--pairs", str(pairs),
         "--downsample", "8", "--folds", "2", "--tv", "1e-4", "--iteration-grid", "10,30",
         "--timing-repeats", "1", "--lensless", str(tmp_path),
         "--json", str(out)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "EK = paper basis, auto side" in proc.stdout      # fit-pairs' defaults
    # its choice: the difference prior, and the ridge where it chose one
    assert re.search(r"EK [\d.]+ s \((source|sensor), (tikhonov [\d.e-]+, )?difference ",
                     proc.stdout)
    assert "LenslessPiCam not available" in proc.stdout      # an empty folder: no peer
    rows = json.loads(out.read_text())
    assert set(rows) == {"SI admm", "EK admm", "SI admm_tv f64"}
    for name in ("SI admm", "EK admm"):
        (row,) = rows[name]
        assert row["pair"] == 2 and row["it"] in (10, 30) and row["tv"] == 1e-4
        assert 10 < row["psnr"] < 40 and 0 < row["ssim"] < 1
    assert rows["SI admm_tv f64"][0]["it"] == rows["SI admm"][0]["it"]
    # The eigen-kernel model's gain on a pair it was not fitted on (im326, 33x60): measured
    # +2.39 dB with fit-pairs' defaults (SI 21.90, EK 24.29 dB; +1.8 dB with the EK weights
    # fixed at --difference 1, source side); at 67x120 the other folds give -0.20..+2.03 dB
    # (research/notes/changelog-measurements.md), so this fold is a test of the gain.
    gain = rows["EK admm"][0]["psnr"] - rows["SI admm"][0]["psnr"]
    assert gain > 0.5, gain
    assert f"EK − SI (admm): {gain:+.2f} dB (EK better on 1 of 1" in proc.stdout
