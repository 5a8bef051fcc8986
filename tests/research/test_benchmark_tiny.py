"""research/benchmark_tiny.py over training seeds: every network once per seed on one dataset,
Table 1 with each method's mean ± sd and its difference to EK-DUN paired by seed, and a
second call that reuses the finished runs."""

from __future__ import annotations

import json

import pytest

from ekdun.data.virtual_bench import VirtualBenchSpec
from ekdun.nets.configs import get_preset
from ekdun.training.trainer import TrainOptions
from research.benchmark_tiny import RUNS, run_tiny_benchmark

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def test_table1_over_seeds_pairs_each_baseline_with_ekdun(tmp_path):
    spec = VirtualBenchSpec(sensor_shape=(16, 16), n_train=4, n_test=2)
    runs = tuple(r for r in RUNS if r[0] in ("ekdun-last-2", "updn"))
    options = TrainOptions(epochs=1, progress=False, threads=1)
    result = run_tiny_benchmark(tmp_path, spec, options, runs=runs, progress=False,
                                log=lambda text: None, seeds=[0, 1])
    rows = result["results"]
    assert [(r["run"], r["seed"]) for r in rows] == [
        ("ekdun-last-2", 0), ("updn", 0), ("ekdun-last-2", 1), ("updn", 1)]
    for r in rows:                      # each network with its own recipe, one folder a seed
        assert (tmp_path / "runs" / r["run"] / f"seed-{r['seed']}" / "checkpoint.pt").is_file()
        assert r["lr"] == get_preset("tiny").training_for(r["model"]).lr
    table = json.loads((tmp_path / "tables" / "table1.json").read_text())
    updn = {e["label"]: e for e in table["over_seeds"]}["UPDN"]
    psnr = {(r["model"], r["seed"]): r["psnr"] for r in rows}
    paired = [psnr[("updn", s)] - psnr[("ekdun", s)] for s in (0, 1)]
    assert updn["reference"] == "EK-DUN (last-2)" and updn["delta_seeds"] == [0, 1]
    assert updn["delta_mean"] == pytest.approx(sum(paired) / 2)
    assert "training seeds 0, 1" in " ".join(table["notes"])
    # finished runs are reused, not retrained: the same numbers again
    again = run_tiny_benchmark(tmp_path, spec, options, runs=runs, progress=False,
                               log=lambda text: None, seeds=[0, 1])
    assert [r["psnr"] for r in again["results"]] == [r["psnr"] for r in rows]
    assert [r["train_seconds"] for r in again["results"]] == [r["train_seconds"] for r in rows]
