"""The analysis/ scripts, each run as a command on a small simulated grid."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.forward.kernelfile import KernelModel, save_kernels
from psfkit.io import read_grid
from psfkit.simulate import BenchConfig, simulate_grid

ANALYSIS = Path(__file__).resolve().parents[2] / "analysis"


SMALL = {"ekdun": {"iterations": 2, "prior": {"widths": [4, 8]}},
         "le-admm-u": {"iterations": 2, "denoiser": {"widths": [4, 8]}},
         "updn": {"iterations": 2, "copies": 1, "denoiser": {"widths": [4, 8]}}}
RUNS = {"ekdun-last-2": ("ekdun", "last-2"), "ekdun-base": ("ekdun", "base"),
        "ekdun-all": ("ekdun", "all"), "le-admm-u": ("le-admm-u", None), "updn": ("updn", None)}


def _run(script: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ANALYSIS / script), *args], capture_output=True,
                          text=True, timeout=300, check=False)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("analysis")
    grid = simulate_grid(root / "grid", BenchConfig(downsample=8), grid_shape=(3, 3),
                         extent=0.8, progress=False)
    model = fit_eigen_grid(read_grid(grid), EigenFitOptions(cv_bases=())).kernel_model()
    learned, initial = root / "learned.npz", root / "initial.npz"
    # a 'learned' model that differs from the measured one in a known way: the corrections
    # negated (Kv' = 2 Kbase - Kv, likewise Kh), so the difference kernels anti-correlate
    k = model.kernels
    save_kernels(learned, KernelModel(kernels=np.stack([k[0], 2 * k[0] - k[1], 2 * k[0] - k[2]]),
                                      sensor_shape=model.sensor_shape))
    save_kernels(initial, KernelModel(kernels=np.stack([model.kernels[0]] * 3),
                                      sensor_shape=model.sensor_shape))
    return grid, learned, initial


@pytest.fixture(scope="module")
def runs(tiny_data, tmp_path_factory) -> dict[str, Path]:
    """The five runs of Tables 1 and 2, each a 1-epoch training of a very small network on
    the 16 × 16 ``tiny_data`` pairs with im6 and im7 held out, which the tables score
    (seconds)."""
    import torch

    from ekdun.data.pairs import PairsDataset
    from ekdun.training import TrainOptions, train

    torch.set_num_threads(1)
    pairs, kernels = tiny_data
    root = tmp_path_factory.mktemp("runs")
    for name, (model, schedule) in RUNS.items():
        overrides = {**SMALL[model], **({"schedule": schedule} if schedule else {})}
        train(root / name, model, kernels, PairsDataset(pairs, holdout=("im6", "im7")), "tiny",
              overrides,
              TrainOptions(epochs=1, batch_size=4, progress=False, threads=1))
    return {name: root / name for name in RUNS}


def _table_rows(path: Path) -> list[str]:
    return [line.split("|")[1].strip() for line in path.read_text().splitlines()
            if line.startswith("| ") and not line.startswith("| Method")
            and not line.startswith("| Eigen")]


def _nontrivial(path: Path, size: int = 10_000) -> None:
    assert path.is_file() and path.stat().st_size > size, path


def test_fig2(bench, tmp_path):
    grid, _, _ = bench
    done = _run("fig2_shift_variance.py", str(grid), "--out", str(tmp_path / "f2"), "--quiet")
    assert done.returncode == 0, done.stderr
    for ext in ("png", "pdf"):
        _nontrivial(tmp_path / "f2" / f"fig2_shift_variance.{ext}")
    doc = json.loads((tmp_path / "f2" / "fig2.json").read_text())
    maes = [r["mae"] for r in doc["centre_column"]]
    assert len(maes) == 3 and min(maes) == 0.0 and max(maes) > 0


def test_fig3(bench, tmp_path):
    _, learned, _ = bench
    done = _run("fig3_weight_maps.py", "--kernels", str(learned), "--out", str(tmp_path / "f3"))
    assert done.returncode == 0, done.stderr
    _nontrivial(tmp_path / "f3" / "fig3_weight_maps.png")
    doc = json.loads((tmp_path / "f3" / "fig3.json").read_text())
    assert doc["sensor_shape"] == [135, 180]
    assert doc["ranges"]["v"][1] == pytest.approx(0.5, abs=0.01)
    done = _run("fig3_weight_maps.py", "--sensor", "64", "96", "--out", str(tmp_path / "f3b"))
    assert done.returncode == 0, done.stderr


def test_fig7(bench, tmp_path):
    grid, learned, initial = bench
    out = tmp_path / "f7"
    done = _run("fig7_learned_kernels.py", str(learned), str(grid), "--initial", str(initial),
                "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    found = re.search(r"learned: v_vs_kernels ([+-]?[\d.]+)", done.stdout)
    assert found and float(found.group(1)) < -0.1, done.stdout     # measured -0.22
    headline = json.loads((out / "compare.json").read_text())["headline"]["learned"]
    assert headline["v_difference_ncc"] == pytest.approx(-1.0, abs=1e-6)
    assert headline["h_difference_ncc"] == pytest.approx(-1.0, abs=1e-6)
    for stem in ("fig7", "fig7_zoom", "fig7_learned_vs_measured", "displacements"):
        _nontrivial(out / "figures" / f"{stem}.png")
        _nontrivial(out / "figures" / f"{stem}.pdf")
    assert json.loads((out / "compare.json").read_text())["initial"] is not None


def test_scripts_fail_in_one_line(bench, tmp_path):
    grid, _, _ = bench
    done = _run("fig7_learned_kernels.py", str(tmp_path / "absent.npz"), str(grid),
                "--out", str(tmp_path / "x"))
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "no such kernel file" in done.stderr
    assert not (tmp_path / "x").exists()


def test_table1_from_runs_then_from_results(runs, tiny_data, tmp_path):
    pairs, _ = tiny_data
    out = tmp_path / "t1"
    done = _run("table1.py", str(runs["le-admm-u"]), str(runs["updn"]),
                str(runs["ekdun-last-2"] / "checkpoint.pt"), "--data", str(pairs),
                "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in out.iterdir()) == ["results.json", "table1.json",
                                                      "table1.md"]
    assert _table_rows(out / "table1.md") == ["Le-ADMM-U", "UPDN", "EK-DUN (last-2)"]
    rows = json.loads((out / "table1.json").read_text())["rows"]
    assert all(np.isfinite(r["psnr"]) and r["parameters"] > 0 for r in rows)
    assert "missing rows" not in done.stdout and "| UPDN |" in done.stdout
    # re-render without evaluating: the same table
    again = tmp_path / "t1b"
    done = _run("table1.py", "--results", str(out / "results.json"), "--out", str(again))
    assert done.returncode == 0, done.stderr
    assert (again / "table1.md").read_text() == (out / "table1.md").read_text()
    assert not (again / "results.json").exists()


def test_table2_from_runs_then_from_results(runs, tiny_data, tmp_path):
    pairs, _ = tiny_data
    out = tmp_path / "t2"
    done = _run("table2.py", *(str(runs[n]) for n in ("ekdun-all", "ekdun-base",
                                                      "ekdun-last-2")),
                "--data", str(pairs), "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    assert _table_rows(out / "table2.md") == ["base only", "last-2", "all"]
    results = json.loads((out / "results.json").read_text())["results"]
    assert {r["schedule"] for r in results} == {"base", "last-2", "all"}
    partial = tmp_path / "partial.json"
    updn = {"model": "updn", "psnr": 1.0, "label": "UPDN"}
    partial.write_text(json.dumps({"results": [results[0], updn]}))
    done = _run("table2.py", "--results", str(partial), "--out", str(tmp_path / "t2b"))
    assert done.returncode == 0, done.stderr
    assert "missing rows: " in done.stdout and len(_table_rows(tmp_path / "t2b" /
                                                               "table2.md")) == 1


def test_table_scripts_fail_in_one_line(runs, tiny_data, tmp_path):
    only_updn = tmp_path / "updn.json"
    only_updn.write_text(json.dumps({"results": [{"model": "updn", "psnr": 1.0,
                                                  "label": "UPDN"}]}))
    cases = [
        (("table1.py",), "give run folders (with --data) or --results"),
        (("table1.py", str(runs["updn"])), "need --data"),
        (("table2.py", "--results", str(only_updn)), "no rows for Table 2"),
        (("table1.py", str(tmp_path / "nope"), "--data", str(tiny_data[0])),
         "no such checkpoint"),
    ]
    for args, message in cases:
        done = _run(*args, "--out", str(tmp_path / "x"))
        assert done.returncode == 2, (args, done.stderr)
        assert len(done.stderr.strip().splitlines()) == 1 and message in done.stderr, args
        assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_fig7_takes_an_ekdun_checkpoint(tmp_path):
    """A real (1-epoch) EK-DUN trained on a tiny virtual-bench dataset (its run folder as
    LEARNED), compared with the dataset's grid; ``--initial`` defaults to the checkpoint's seed
    kernels."""
    import torch

    from ekdun.data.pairs import PairsDataset
    from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench
    from ekdun.training import TrainOptions, train

    torch.set_num_threads(1)
    data = make_virtual_bench(tmp_path / "data", VirtualBenchSpec(
        sensor_shape=(32, 32), n_train=4, n_test=1, grid_shape=(3, 3)), progress=False)
    # the dataset's oracles (research/; make-dataset wrote them until issue 44)
    from research.oracles import write_dataset_oracles

    write_dataset_oracles(data)
    # the measured seed: psfkit fit-eigen of the dataset's grid (paper basis)
    fit = fit_eigen_grid(read_grid(data / "grid"),
                         EigenFitOptions(basis="paper", convention="auto"))
    kernels = save_kernels(tmp_path / "seed.npz", fit.kernel_model())
    options = TrainOptions(epochs=1, batch_size=4, progress=False, threads=1)
    train(tmp_path / "run", "ekdun", kernels, PairsDataset(data / "train"), "tiny",
          SMALL["ekdun"], options)
    # a second start: one PSF (Kv = Kh = Kbase), flow-parameterised kernels
    from dataclasses import replace

    import numpy as np

    from psfkit.forward.kernelfile import load_kernels

    seed = load_kernels(kernels)
    one = save_kernels(tmp_path / "one.npz", replace(
        seed, kernels=np.repeat(seed.kernels[:1], len(seed.kernels), axis=0)))
    from research.kernel_models import train as train_study

    train_study(tmp_path / "run1", "ekdun", one, PairsDataset(data / "train"), "tiny",
                {**SMALL["ekdun"], "kernel_param": "flow"}, options)
    out = tmp_path / "f7"
    done = _run("fig7_learned_kernels.py", str(tmp_path / "run"), str(data / "grid"),
                "--out", str(out), "--quiet", "--one-psf", str(tmp_path / "run1"))
    assert done.returncode == 0, done.stderr
    assert "learned: v_vs_kernels" in done.stdout and "initial: v_vs_kernels 1.000" in done.stdout
    _nontrivial(out / "figures" / "fig7.png")
    _nontrivial(out / "figures" / "fig7_starts.png")
    doc = json.loads((out / "compare.json").read_text())
    assert doc["initial"] is not None
    split = doc["kernel_change"]["learned_vs_initial"]
    assert sum(split["v"]["fractions"].values()) == pytest.approx(1.0)
    text = (out / "fig7_caption.md").read_text()
    assert "one PSF: displacement corr." in text and "pedestal" in text

    # the dataset lists an operator oracle of the learned convention: used by default
    from ekdun.training import export_kernels
    from research.compare import compare_kernels

    convention = seed.convention
    oracle = data / "oracle" / f"paper_{convention}.npz"
    assert f"oracle: {oracle} (operator oracle, {convention} side" in done.stdout
    assert "vs oracle, learned: seeded from the measured fit: v_diff_ncc" in done.stdout
    assert "vs oracle, learned: one PSF: v_diff_ncc" in done.stdout
    assert "vs oracle, measured fit: v_diff_ncc" in done.stdout
    assert "Against the operator oracle (" in text and "measured fit: difference NCC" in text
    numbers = json.loads((out / "oracle.json").read_text())
    assert numbers["oracle"] == str(oracle) and numbers["convention"] == convention
    vs = numbers["vs_oracle"]
    assert set(vs) == {"learned: seeded from the measured fit", "learned: one PSF",
                       "measured fit"}
    # the numbers are those of the learned kernels against the oracle (the reference)
    expected = compare_kernels(export_kernels(tmp_path / "run" / "checkpoint.pt"),
                               oracle).learned.numbers()
    got = vs["learned: seeded from the measured fit"]
    for key in ("v_diff_ncc", "h_diff_ncc", "v_epe_px", "h_epe_px"):
        assert got[key] == pytest.approx(expected[key], abs=1e-9), key
    assert got["angles_deg"] == pytest.approx(expected["angles_deg"], abs=1e-6)
    assert len(got["angles_deg"]) == 3 and -1 <= got["v_diff_ncc"] <= 1

    # --no-oracle: no oracle row (a shorter figure), no oracle numbers
    bare = tmp_path / "f7bare"
    done = _run("fig7_learned_kernels.py", str(tmp_path / "run"), str(data / "grid"),
                "--out", str(bare), "--quiet", "--one-psf", str(tmp_path / "run1"),
                "--no-oracle")
    assert done.returncode == 0, done.stderr
    assert "oracle" not in done.stdout.replace(str(bare), "")
    assert not (bare / "oracle.json").exists()
    assert "oracle" not in (bare / "fig7_caption.md").read_text()
    import matplotlib.pyplot as plt

    rows_with, rows_without = (plt.imread(d / "figures" / "fig7_starts.png").shape[0]
                               for d in (out, bare))
    # 4 rows (measured, oracle, 2 learned) against 3: 1.2 in a row, 1 in of colour bars and title
    assert rows_with / rows_without == pytest.approx(5.8 / 4.6, rel=0.08)

    # an explicit oracle of the other convention, or of another sensor, is refused
    other = data / "oracle" / f"paper_{'sensor' if convention == 'source' else 'source'}.npz"
    wrong_size = save_kernels(tmp_path / "oracle64.npz", replace(
        load_kernels(oracle), sensor_shape=(64, 64)))
    for path, message in ((other, "oracle convention"), (wrong_size, "oracle sensor 64x64")):
        done = _run("fig7_learned_kernels.py", str(tmp_path / "run"), str(data / "grid"),
                    "--out", str(tmp_path / "f7x"), "--oracle", str(path))
        assert done.returncode == 2, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and message in done.stderr
        assert str(path) in done.stderr and not (tmp_path / "f7x").exists()


def test_fig7_refuses_a_checkpoint_without_eigen_kernels(runs, bench, tmp_path):
    grid, _, _ = bench
    done = _run("fig7_learned_kernels.py", str(runs["updn"] / "checkpoint.pt"), str(grid),
                "--out", str(tmp_path / "f7c"))
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "only EK-DUN has eigen kernels" in done.stderr and not (tmp_path / "f7c").exists()
