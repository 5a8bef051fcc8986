"""Table 1 on a lent GPU within its time (issue 45): the trainings at once, stopped at a
deadline, evaluated, and autocast priced on the trained networks.

    python -m research.table1_device OUT [--sensor 256 256] [--n-train 2000] [--n-test 64]
        [--epochs 20] [--seeds 0,1,2] [--runs ekdun-last-2,updn,le-admm-u]
        [--stop-at 420] [--device auto]

A lent device gives a session about 15 minutes in all and 10 per command, so the runs that
:mod:`research.benchmark_tiny` trains one after the other train here side by side, one
process each (``tiny`` networks leave most of a GPU idle):

1. the virtual bench (the dense model on the device) and the seed kernels of its grid;
2. every (run, seed) in its own process (``python -m research.table1_device OUT --worker RUN
   SEED``), each network at its recipe and the default AMP (fp16 on CUDA); at ``--stop-at``
   seconds from the start the processes still training get ``SIGTERM`` and keep their last
   finished epoch (the trainer writes an epoch's files together);
3. every run evaluated on the test pairs (the epochs each reached are in the table), into
   ``OUT/tables`` (:func:`ekdun.evaluation.write_tables`);
4. :mod:`research.precision_check` of every trained network on the device, fp16 against
   float32, into ``OUT/precision``.

Everything is resumable: called again on the same (warm) machine, a finished run is reused
and a stopped one continues from its checkpoint.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from ekdun.data.pairs import PairsDataset
from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench
from ekdun.device import resolve_device
from ekdun.evaluation import LPIPSMetric, evaluate_model, write_tables
from ekdun.evaluation.evaluate import recorded_optical_center
from ekdun.evaluation.tables import label_for
from ekdun.nets.builder import network_from_checkpoint
from ekdun.nets.checkpoint import load_checkpoint
from ekdun.training.trainer import CHECKPOINT, TrainOptions, train
from psfkit.cli import run_cli
from psfkit.cli.main import add_debug_option
from psfkit.cli.parser import OneLineArgumentParser
from research.benchmark_tiny import RUNS, fit_seed_kernels, int_list, run_names
from research.precision_check import precision_check

#: Seconds a stopped training has to finish writing its epoch before it is killed.
GRACE_S = 60


def prepare(out: Path, spec: VirtualBenchSpec, device: torch.device) -> Path:
    """The bench's dataset (computed on ``device``) and its seed kernels; returns the
    dataset's folder."""
    data = make_virtual_bench(out / "dataset", spec, progress=False, device=device,
                              workers=max(1, min(8, (os.cpu_count() or 2) // 2)))
    if not (out / "kernels_fit.npz").is_file():
        fit_seed_kernels(data, out / "kernels_fit.npz")
    return data


def run_dir(out: Path, run: str, seed: int) -> Path:
    """Where run ``run`` with training seed ``seed`` trains."""
    return out / "runs" / run / f"seed-{seed}"


def train_one(out: Path, run: tuple[str, str, dict[str, Any]], seed: int, epochs: int | None,
              device: str) -> None:
    """Train (or resume) one run on ``out``'s dataset, at its recipe and the default AMP."""
    name, model, overrides = run
    folder = run_dir(out, name, seed)
    ckpt = folder / CHECKPOINT
    options = TrainOptions(epochs=epochs, seed=seed, device=device, progress=False,
                           threads=1)
    target = options.resolve("tiny", model).epochs
    if ckpt.is_file() and load_checkpoint(ckpt)["metadata"].get("epoch", 0) >= target:
        return
    train(folder, model, out / "kernels_fit.npz", PairsDataset(out / "dataset" / "train"),
          "tiny", dict(overrides), options, resume=ckpt.is_file(), overwrite=not ckpt.is_file())


def train_all(out: Path, jobs: Sequence[tuple[str, int]], epochs: int | None, device: str,
              stop_at: float, started: float, log: Any = print) -> None:
    """Every ``(run, seed)`` in its own process at once; those still running ``stop_at``
    seconds after ``started`` are stopped (``SIGTERM``, then killed after ``GRACE_S``)."""
    command = [sys.executable, "-m", "research.table1_device", str(out), "--device", device]
    if epochs is not None:
        command += ["--epochs", str(epochs)]
    # the workers import research/ from this checkout, wherever OUT is
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(root), os.environ.get("PYTHONPATH")) if p)}
    procs = {job: subprocess.Popen([*command, "--worker", job[0], str(job[1])], cwd=root,
                                   env=env) for job in jobs}
    while any(p.poll() is None for p in procs.values()):
        if time.monotonic() - started > stop_at:
            log(f"stop at {stop_at:.0f} s: {sum(p.poll() is None for p in procs.values())} "
                "trainings still running keep their last epoch")
            _stop(procs.values())
            break
        time.sleep(2)
    for job, p in procs.items():
        if p.returncode not in (0, -signal.SIGTERM):
            log(f"{job[0]} seed {job[1]}: exit {p.returncode}")


def _stop(procs: Any) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + GRACE_S
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def evaluate_all(out: Path, jobs: Sequence[tuple[str, int]], device: torch.device
                 ) -> list[dict[str, Any]]:
    """Every trained run evaluated on the test pairs (on ``device``); rows as
    :func:`research.benchmark_tiny.train_and_evaluate`'s, with the epochs reached."""
    runs = {r[0]: r for r in RUNS}
    test_set = PairsDataset(out / "dataset" / "test")
    lpips = LPIPSMetric(None)
    rows = []
    for name, seed in jobs:
        ckpt = run_dir(out, name, seed) / CHECKPOINT
        if not ckpt.is_file():
            continue
        model, doc = network_from_checkpoint(ckpt)
        meta = doc["metadata"]
        _name, model_name, overrides = runs[name]
        row = evaluate_model(model.to(device), test_set,
                             label_for(model_name, overrides.get("schedule")), lpips,
                             device=device, optical_center=recorded_optical_center(meta))
        row.update({"run": name, "model": model_name, "schedule": overrides.get("schedule"),
                    "seed": seed, "epochs": meta["epoch"],
                    "lr": meta.get("training", {}).get("lr"),
                    "train_seconds": sum(h["seconds"] for h in meta["history"]),
                    "final_train_loss": meta["history"][-1]["train_loss"]})
        rows.append(row)
    return rows


def table1_device(out: str | Path, spec: VirtualBenchSpec,
                  runs: Sequence[tuple[str, str, dict[str, Any]]], seeds: Sequence[int],
                  epochs: int | None = 20, stop_at: float = 420.0, device: str = "auto",
                  log: Any = print) -> dict[str, Any]:
    """Steps 1–4 of the module docstring; returns the rows and the precision check."""
    started = time.monotonic()
    out = Path(out)
    where = resolve_device(device)
    prepare(out, spec, where)
    log(f"dataset and seed kernels ready ({time.monotonic() - started:.0f} s)")
    jobs = [(r[0], s) for s in seeds for r in runs]
    train_all(out, jobs, epochs, str(where), stop_at, started, log)
    log(f"trainings done ({time.monotonic() - started:.0f} s)")
    rows = evaluate_all(out, jobs, where)
    for r in rows:
        log(f"{r['run']} seed {r['seed']}: {r['psnr']:.2f} dB after {r['epochs']} epochs "
            f"({r['train_seconds']:.0f} s of training)")
    name = torch.cuda.get_device_name(where) if where.type == "cuda" else "the CPU"
    write_tables(out / "tables", rows, [
        f"Virtual bench {spec.sensor_shape[0]}x{spec.sensor_shape[1]}, {spec.n_train} / "
        f"{spec.n_test} pairs, preset tiny (each network's recipe), up to "
        f"{epochs} epochs (each row's epochs are those reached by {stop_at:.0f} s), training "
        f"seeds {', '.join(map(str, seeds))}, {len(jobs)} trainings at once on {name}."])
    ckpts = [str(run_dir(out, r["run"], r["seed"]) / CHECKPOINT) for r in rows]
    precision = precision_check(out / "precision", ckpts, str(out / "dataset" / "test"),
                                ["fp16"], where) if ckpts else None
    log(f"evaluated ({time.monotonic() - started:.0f} s)")
    return {"rows": rows, "precision": precision}


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m research.table1_device``."""
    p = OneLineArgumentParser(prog="python -m research.table1_device",
                              description="Table 1 on a lent GPU: trainings side by side, "
                                          "stopped at a deadline, evaluated (issue 45).")
    add_debug_option(p)
    p.add_argument("out", help="output folder (resumable)")
    p.add_argument("--sensor", type=int, nargs=2, default=(256, 256), metavar=("H", "W"))
    p.add_argument("--n-train", type=int, default=2000)
    p.add_argument("--n-test", type=int, default=64)
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--seeds", type=int_list, default=[0, 1, 2])
    p.add_argument("--runs", type=run_names,
                   default=tuple(r for r in RUNS if r[0] in ("ekdun-last-2", "updn",
                                                             "le-admm-u")))
    p.add_argument("--stop-at", type=float, default=420.0,
                   help="seconds from the start after which trainings stop (default 420)")
    p.add_argument("--device", default="auto")
    p.add_argument("--worker", nargs=2, metavar=("RUN", "SEED"), help=argparse.SUPPRESS)
    p.set_defaults(func=_run)
    return p


def _run(args: argparse.Namespace) -> int:
    if args.worker:
        run = run_names(args.worker[0])[0]
        train_one(Path(args.out), run, int(args.worker[1]), args.epochs, args.device)
        return 0
    spec = VirtualBenchSpec(sensor_shape=tuple(args.sensor), n_train=args.n_train,
                            n_test=args.n_test)
    table1_device(args.out, spec, args.runs, args.seeds, args.epochs, args.stop_at,
                  args.device, log=lambda text: print(text, file=sys.stderr))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``python -m research.table1_device`` with ``argv``; returns the exit code."""
    return run_cli("research.table1_device", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
