"""research/table1_device.py (issue 45): Table 1's trainings side by side on a lent GPU,
stopped at a deadline, evaluated and priced under autocast; resumable."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from ekdun.data.virtual_bench import VirtualBenchSpec
from research import table1_device as t1
from research.benchmark_tiny import RUNS

_POPEN = subprocess.Popen


def _sleeper() -> subprocess.Popen:
    return _POPEN([sys.executable, "-c", "import time; time.sleep(60)"])


def test_a_stopped_process_gets_sigterm() -> None:
    p = _sleeper()
    t0 = time.monotonic()
    t1._stop([p])
    assert p.returncode == -signal.SIGTERM and time.monotonic() - t0 < 10


def test_trainings_still_running_at_the_deadline_are_stopped(tmp_path, monkeypatch) -> None:
    launched = []

    def fake_popen(command, **kwargs):
        launched.append(command)
        return _sleeper()

    monkeypatch.setattr(t1.subprocess, "Popen", fake_popen)
    said = []
    t0 = time.monotonic()
    t1.train_all(tmp_path, [("updn", 0), ("le-admm-u", 1)], 3, "cpu", stop_at=0.5,
                 started=t0, log=said.append)
    assert time.monotonic() - t0 < 15
    assert [c[-3:] for c in launched] == [["--worker", "updn", "0"],
                                          ["--worker", "le-admm-u", "1"]]
    assert all(c[c.index("--epochs") + 1] == "3" for c in launched)
    assert said and "2 trainings still running" in said[0]


@pytest.mark.e2e
@pytest.mark.slow
def test_the_table_is_trained_evaluated_priced_and_resumed(tmp_path) -> None:
    spec = VirtualBenchSpec(sensor_shape=(16, 16), n_train=4, n_test=2)
    runs = [r for r in RUNS if r[0] == "le-admm-u"]
    first = t1.table1_device(tmp_path, spec, runs, [0], epochs=1, stop_at=600, device="cpu",
                             log=lambda text: None)
    (row,) = first["rows"]
    assert row["run"] == "le-admm-u" and row["epochs"] == 1 and row["seed"] == 0
    assert (tmp_path / "tables" / "table1.md").is_file()
    (priced,) = first["precision"]["runs"]
    assert priced["amp"] == "fp16" and len(priced["pairs"]) == 2
    ckpt = t1.run_dir(tmp_path, "le-admm-u", 0) / "checkpoint.pt"
    stamp = ckpt.stat().st_mtime_ns
    again = t1.table1_device(tmp_path, spec, runs, [0], epochs=1, stop_at=600, device="cpu",
                             log=lambda text: None)
    # the finished run is reused, not trained again
    assert ckpt.stat().st_mtime_ns == stamp
    assert again["rows"][0]["psnr"] == pytest.approx(row["psnr"], abs=1e-9)
