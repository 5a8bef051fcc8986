"""The ``tiny`` benchmark: dataset → eigen-kernel fit → 5 trainings → Tables 1 and 2
(``ekdun benchmark-tiny`` until issue 44; the paper's tables at a CPU size, a research run).

    python -m research.benchmark_tiny OUT [--epochs N] [--n-train 96] [--n-test 24] [--seed 0]
        [--seeds 0,1,2] [--sensor 128 128] [--runs ekdun-last-2,le-admm-u,updn]

``run_tiny_benchmark(out)`` builds the virtual-bench dataset (``out/dataset``), fits the
eigen-kernel seed model to the dataset's PSF grid with psfkit (``out/kernels_fit.npz``),
trains EK-DUN (last-2, base only, all), Le-ADMM-U and UPDN (``out/runs/NAME``) and evaluates
them on the held-out test pairs (``out/tables``). Every step is resumable: a finished run is
reused, an interrupted one resumes from its last checkpoint.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from ekdun.data.pairs import PairsDataset
from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench
from ekdun.errors import ConfigurationError
from ekdun.evaluation import LPIPSMetric, evaluate_model, write_tables
from ekdun.evaluation.evaluate import recorded_optical_center
from ekdun.evaluation.tables import label_for
from ekdun.flag_ranges import flag
from ekdun.nets.builder import network_from_checkpoint
from ekdun.nets.checkpoint import load_checkpoint
from ekdun.training.trainer import CHECKPOINT, TrainOptions, train
from psfkit.cli import run_cli
from psfkit.cli.main import add_debug_option
from psfkit.cli.parser import OneLineArgumentParser
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.forward.kernelfile import save_kernels
from psfkit.io import read_grid
from psfkit.io.atomic import atomic_file

RUNS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("ekdun-last-2", "ekdun", {"schedule": "last-2"}),
    ("ekdun-base", "ekdun", {"schedule": "base"}),
    ("ekdun-all", "ekdun", {"schedule": "all"}),
    ("le-admm-u", "le-admm-u", {}),
    ("updn", "updn", {}),
)


def fit_seed_kernels(dataset_root: Path, out: Path, convention: str = "auto") -> Path:
    """``psfkit fit-eigen`` of the dataset's grid (paper basis) into ``out``."""
    result = fit_eigen_grid(read_grid(dataset_root / "grid"),
                            EigenFitOptions(basis="paper", convention=convention))
    return save_kernels(out, result.kernel_model())


def train_and_evaluate(run: tuple[str, str, dict[str, Any]], seed: int,
                        kernels: Path, train_set: PairsDataset, test_set: PairsDataset,
                        preset: str, options: TrainOptions, lpips: LPIPSMetric,
                        run_dir: Path) -> dict[str, Any]:
    """One training (resumed or reused when its checkpoint is there) and its evaluation."""
    run_name, model_name, overrides = run
    options = replace(options, seed=seed)
    epochs = options.resolve(preset, model_name).epochs
    ckpt = run_dir / CHECKPOINT
    done = ckpt.is_file() and load_checkpoint(ckpt)["metadata"].get("epoch", 0) >= epochs
    if not done:
        # the benchmark's own folder: a run killed before its first checkpoint restarts
        train(run_dir, model_name, kernels, train_set, preset, overrides, options,
              resume=ckpt.is_file(), overwrite=not ckpt.is_file())
    model, doc = network_from_checkpoint(ckpt)
    meta = doc["metadata"]
    schedule = overrides.get("schedule")
    row = evaluate_model(model, test_set, label_for(model_name, schedule), lpips,
                         optical_center=recorded_optical_center(meta))
    row.update({"run": run_name, "model": model_name, "schedule": schedule, "seed": seed,
                "epochs": meta["epoch"], "lr": meta.get("training", {}).get("lr"),
                "train_seconds": sum(h["seconds"] for h in meta["history"]),
                "final_train_loss": meta["history"][-1]["train_loss"]})
    return row


def run_tiny_benchmark(out: str | os.PathLike, spec: VirtualBenchSpec | None = None,
                       options: TrainOptions | None = None, preset: str = "tiny",
                       runs: tuple[tuple[str, str, dict[str, Any]], ...] = RUNS,
                       lpips_weights: str | None = None, progress: bool = True,
                       log: Any = print, seeds: Sequence[int] | None = None
                       ) -> dict[str, Any]:
    """Run the whole benchmark; returns ``{"results": [...], "timings": {...}}``.

    ``seeds``: training seeds (default: ``options.seed`` alone), each network trained once
    per seed on the same dataset; with several, the runs go to ``out/runs/NAME/seed-S`` and
    the tables add each row's mean ± sd over seeds and its difference to EK-DUN paired by
    seed.
    """
    out = Path(out)
    spec = spec or VirtualBenchSpec()
    options = options or TrainOptions(progress=progress, threads=1)
    seeds = list(seeds) if seeds else [options.seed]
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    data = make_virtual_bench(out / "dataset", spec, progress=progress)
    timings["dataset_s"] = time.perf_counter() - t0
    log(f"dataset ready: {data} ({timings['dataset_s']:.1f} s)")
    t0 = time.perf_counter()
    kernels = out / "kernels_fit.npz"
    if not kernels.is_file():
        fit_seed_kernels(data, kernels)
    timings["fit_eigen_s"] = time.perf_counter() - t0
    log(f"eigen kernels: {kernels} ({timings['fit_eigen_s']:.1f} s)")
    train_set, test_set = PairsDataset(data / "train"), PairsDataset(data / "test")
    lpips = LPIPSMetric(lpips_weights)
    if not lpips.available:
        log(lpips.reason)
    results = []
    for seed in seeds:
        for run in runs:
            run_dir = out / "runs" / run[0] / (f"seed-{seed}" if len(seeds) > 1 else "")
            t0 = time.perf_counter()
            row = train_and_evaluate(run, seed, kernels, train_set, test_set, preset,
                                      options, lpips, run_dir)
            timings[f"train_{run[0]}_seed{seed}_s"] = time.perf_counter() - t0
            results.append(row)
            log(f"{run[0]} seed {seed}: PSNR {row['psnr']:.2f} dB, SSIM {row['ssim']:.4f}, "
                f"train {row['train_seconds']:.0f} s")
    epochs = sorted({r["epochs"] for r in results})
    notes = [f"Virtual bench ({spec.grid_shape[0]}x{spec.grid_shape[1]} PSF grid, dense "
             f"shift-variant forward model, half field of view {spec.half_fov_deg} deg, "
             f"{spec.n_train} training / {spec.n_test} held-out test pairs of "
             f"{spec.sensor_shape[0]}x{spec.sensor_shape[1]} px), preset {preset} (each "
             f"network's recipe), epochs {', '.join(map(str, epochs))}, training seeds "
             f"{', '.join(map(str, seeds))}, torch threads {torch.get_num_threads()}.",
             "Runtime: median over test images, batch 1, on a shared CPU (noisy).",
             lpips.reason or "LPIPS: AlexNet weights from a local file."]
    write_tables(out / "tables", results, notes)
    with atomic_file(out / "tables" / "timings.json") as tmp:
        tmp.write_text(json.dumps(timings, indent=1) + "\n", encoding="utf-8")
    return {"results": results, "timings": timings}


def comma_list(cast: Callable[[str], Any], what: str, valid: Callable[[Any], bool]
               ) -> Callable[[str], list[Any]]:
    """An argparse type for ``"a,b,c"``: each item ``cast``, all ``valid`` (``what`` names
    them in the one-line error)."""
    def parse(text: str) -> list[Any]:
        try:
            values = [cast(v) for v in text.split(",") if v.strip()]
        except ValueError:
            values = []
        if not values or not all(valid(v) for v in values):
            raise argparse.ArgumentTypeError(f"expected {what} separated by commas, got "
                                             f"{text!r}")
        return values
    return parse


int_list = comma_list(int, "integers >= 0", lambda v: v >= 0)


def run_names(text: str) -> tuple[tuple[str, str, dict[str, Any]], ...]:
    """An argparse type: comma-separated names of :data:`RUNS`, their runs in that order."""
    known = {r[0]: r for r in RUNS}
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown run {', '.join(unknown) or text!r} "
                                         f"(use {', '.join(known)})")
    return tuple(known[n] for n in names)


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m research.benchmark_tiny`` (the flags of the former
    ``ekdun benchmark-tiny``)."""
    p = OneLineArgumentParser(prog="python -m research.benchmark_tiny",
                              description="Dataset, eigen-kernel fit, 5 trainings, Tables 1 "
                                          "and 2 (tiny preset, CPU); resumable.")
    add_debug_option(p)
    p.add_argument("out", help="benchmark folder (resumable)")
    p.add_argument("--epochs", type=flag("--epochs"), help="override the preset's epochs")
    p.add_argument("--n-train", type=flag("--n-train"), default=96,
                   help="training scenes (default 96)")
    p.add_argument("--n-test", type=flag("--n-test"), default=24, help="test scenes (default 24)")
    p.add_argument("--threads", type=flag("--threads"), default=1,
                   help="torch threads (default 1, fastest on a shared 2-core machine)")
    p.add_argument("--seed", type=flag("--seed"), default=0,
                   help="seed of the dataset (diffuser, scenes, noise) and of the trainings")
    p.add_argument("--seeds", type=int_list, default=None,
                   help="training seeds, comma-separated (default: --seed); each network is "
                        "trained once per seed on the same dataset, and the tables give mean "
                        "± sd and the difference to EK-DUN paired by seed")
    p.add_argument("--sensor", type=int, nargs=2, default=(64, 64), metavar=("H", "W"),
                   help="sensor size of the dataset (default 64 64)")
    p.add_argument("--runs", type=run_names, default=RUNS,
                   help=f"runs, comma-separated (default all: "
                        f"{','.join(r[0] for r in RUNS)})")
    p.add_argument("--lpips-weights", help="local AlexNet weights for LPIPS")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)
    return p


def _run(args: argparse.Namespace) -> int:
    from ekdun.training import TrainOptions

    torch.set_num_threads(args.threads)
    if min(args.sensor) < 16:
        raise ConfigurationError(f"--sensor must be at least 16 16, got {args.sensor}")
    spec = VirtualBenchSpec(sensor_shape=tuple(args.sensor), n_train=args.n_train,
                            n_test=args.n_test, seed=args.seed)
    options = TrainOptions(epochs=args.epochs, progress=not args.quiet, threads=args.threads,
                           seed=args.seed)

    def say(text: str) -> None:
        if not args.quiet:
            print(text, file=sys.stderr)

    result = run_tiny_benchmark(args.out, spec, options, runs=args.runs,
                                lpips_weights=args.lpips_weights, progress=not args.quiet,
                                log=say, seeds=args.seeds)
    say(json.dumps(result["timings"]))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``python -m research.benchmark_tiny`` with ``argv``; returns the exit code."""
    return run_cli("research.benchmark_tiny", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
