"""Benchmark: how much of the model mismatch does EK-DUN's U-Net absorb? (issue 24, item 3)

Table 2's gain (last-2 − base only) is the eigen-kernel model's gain *after* the network has
learned to correct whatever its physics gets wrong. This measures the gain with the physics
known exactly and frozen, against the gain the physics alone gives, on one virtual-bench
dataset (``ekdun make-dataset``, source-side dense model):

- **oracle SI**: the shift-invariant model closest to the dense operator over the dataset's
  scenes (:func:`research.oracles.operator_oracle` with basis ``si``), and **oracle EK**:
  the eigen-kernel one (``DATA/oracle/paper_source.npz``, the same least squares, paper
  basis);
- **classical** (no learning): ADMM-TV with each oracle (:class:`ModelReconstructor`, the
  solver of ``ekdun admm --kernels``), the TV weight chosen on ``--tune`` training pairs for
  each model alike: the gain the better physics gives by itself;
- **learned, kernels frozen** (``kernel_lr_scale = 0``): EK-DUN base only with the SI oracle
  as its kernel, and EK-DUN ``--schedule`` (default last-2) with the EK oracle, trained alike
  (preset, epochs, training seeds).

absorbed = 1 − (learned gain) / (classical gain): the share of the physics gain that the
network makes up for without it. It splits in two, exactly: the network's correction of the SI
model (learned SI − classical SI, over the classical gain) and its shortfall with the exact
physics (classical EK − learned EK, over the classical gain; where a small or short-trained
network ends below ADMM-TV with the EK oracle, the gain it does not show is not absorbed by
it but missed by both). ``--half-fov`` and ``--n-train`` take lists (a sweep: one
dataset per field of view; the first N training pairs of the largest dataset for each N).
``--data`` uses an existing dataset instead (its own field of view; ``--n-train`` defaults to
all its training pairs), e.g. the identifiable 128² bench of Table 2.

    python -m research.unet_absorption --out runs/absorb              # 64², tiny
    python -m research.unet_absorption --out runs/absorb --half-fov 15,30,45 \\
        --learned none                                                        # classical only
    python -m research.unet_absorption --out runs/absorb128 --data DATA128P6 --seeds 0
    python -m research.unet_absorption --out runs/absorb --n-train 24,96 --seeds 0,1,2

Prints one Markdown table, measured in this run (finished runs and classical scores are
reused: resumable, and processes with different ``--seeds`` may share one ``--out``).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ekdun.data.bench_spec import VirtualBenchSpec
from ekdun.data.pairs import PairsDataset
from ekdun.data.virtual_bench import (
    make_virtual_bench,
    read_manifest,
)
from ekdun.evaluation.metrics import psnr, ssim
from ekdun.nets.builder import network_from_checkpoint
from ekdun.nets.checkpoint import load_checkpoint
from ekdun.reconstruction.classical import ClassicalOptions, ModelReconstructor
from ekdun.training import TrainOptions, train
from ekdun.training.trainer import CHECKPOINT
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.io.jsonable import write_json
from research.oracles import operator_oracle, oracle_file, write_dataset_oracles

TV_GRID = (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2)


def dataset(out: Path, half_fov: float, n_train: int, args: argparse.Namespace) -> Path:
    """The virtual-bench dataset of one field of view (made once, cached)."""
    spec = VirtualBenchSpec(sensor_shape=tuple(args.sensor), n_train=n_train,
                            n_test=args.n_test, photons=args.photons, half_fov_deg=half_fov)
    folder = out / f"data-fov{half_fov:g}-n{n_train}"
    if read_manifest(folder) is None:
        t0 = time.perf_counter()
        make_virtual_bench(folder, spec, progress=False)
        print(f"made {folder} in {time.perf_counter() - t0:.0f} s", flush=True)
    return folder


def oracles(data: Path, out: Path) -> dict[str, Path]:
    """``{"si": ..., "si_as_paper": ..., "ek": ...}`` kernel files of the dataset's oracles.

    ``ek`` is the dataset's own operator oracle (source side; written into the dataset by
    :func:`~research.oracles.write_dataset_oracles` where it has none); the SI oracle (the
    same least squares, basis ``si``, as many scenes) is computed once into ``out``, not into
    the dataset. ``si_as_paper`` is it in the paper basis (``Kv = Kh = Kbase``), the form EK-DUN
    reads; base only never uses ``Kv``, ``Kh``.
    """
    if read_manifest(data) is None:
        raise SystemExit(f"{data}: not a virtual-bench dataset (ekdun make-dataset)")
    write_dataset_oracles(data)
    manifest = read_manifest(data)
    ek = oracle_file(data, "source")
    if manifest is None or ek is None:
        raise SystemExit(f"{data}: no source-side oracle")
    spec = VirtualBenchSpec.from_dict(manifest["spec"])
    folder = out / "si_oracles" / data.name
    folder.mkdir(parents=True, exist_ok=True)
    si, si_paper = folder / "si_source.npz", folder / "si_as_paper.npz"
    if not si.is_file():
        n = manifest["oracle"]["files"]["source"]["operator_record"]["n_scenes"]
        save_kernels(si, operator_oracle(spec, "source", "si", n_scenes=n,
                                         check_convergence=False).model)
    if not si_paper.is_file():
        model = load_kernels(si)
        save_kernels(si_paper, replace(load_kernels(ek),
                                       kernels=np.repeat(model.kernels, 3, axis=0),
                                       provenance={**model.provenance,
                                                   "note": "SI oracle as Kbase = Kv = Kh"}))
    return {"si": si, "si_as_paper": si_paper, "ek": ek}


def _scores(images: list[np.ndarray], truth: list[np.ndarray]) -> dict[str, float]:
    out = torch.as_tensor(np.stack(images)).clamp(0, 1)
    ref = torch.as_tensor(np.stack(truth))
    return {"psnr": float(psnr(out, ref).mean()), "ssim": float(ssim(out, ref).mean())}


def classical(model: KernelModel, data: Path, tune: int, iterations: int,
              tv_grid: tuple[float, ...] = TV_GRID) -> dict[str, Any]:
    """ADMM-TV with ``model``: TV weight chosen on ``tune`` training pairs, scored on test."""
    train_set, test_set = PairsDataset(data / "train"), PairsDataset(data / "test")
    best = None
    for tv in tv_grid:
        rec = ModelReconstructor(model, ClassicalOptions(tv=tv, iterations=iterations))
        pairs = [train_set[i] for i in range(tune)]
        score = _scores([rec(y.numpy()).image for _, y in pairs],
                        [x.numpy() for x, _ in pairs])["psnr"]
        if best is None or score > best[1]:
            best = (tv, score)
    assert best is not None
    if best[0] in (tv_grid[0], tv_grid[-1]):
        print(f"  note: TV weight {best[0]:g} is at the end of the grid {tv_grid}", flush=True)
    rec = ModelReconstructor(model, ClassicalOptions(tv=best[0], iterations=iterations))
    images, truth = [], []
    for i in range(len(test_set)):
        x, y = test_set[i]
        images.append(rec(y.numpy()).image)
        truth.append(x.numpy())
    return {"tv": best[0], **_scores(images, truth)}


def classical_cached(out: Path, name: str, kernels: Path, data: Path,
                     args: argparse.Namespace) -> dict[str, Any]:
    """:func:`classical`, its score kept in ``out/classical`` for the same inputs and settings."""
    key = {"data": str(data.resolve()), "kernels": str(kernels.resolve()), "tune": args.tune,
           "iterations": args.iterations, "tv_grid": list(args.tv_grid)}
    cache = out / "classical" / f"{data.name}-{name}.json"
    if cache.is_file():
        kept = json.loads(cache.read_text())
        if kept.get("key") == key:
            return kept["score"]
    score = classical(load_kernels(kernels), data, args.tune, args.iterations,
                      tuple(args.tv_grid))
    cache.parent.mkdir(parents=True, exist_ok=True)
    write_json(cache, {"key": key, "score": score})   # atomic: --out may be shared
    return score


def learned(run: Path, kernels: Path, schedule: str, data: Path, n_train: int,
            args: argparse.Namespace, train_seed: int) -> dict[str, Any]:
    """EK-DUN with frozen kernels, trained on the first ``n_train`` pairs; test PSNR/SSIM."""
    ckpt = run / CHECKPOINT
    if not (ckpt.is_file() and load_checkpoint(ckpt)["metadata"]["epoch"] >= args.epochs):
        full = PairsDataset(data / "train")
        subset = torch.utils.data.Subset(full, range(min(n_train, len(full))))
        options = TrainOptions(epochs=args.epochs, kernel_lr_scale=0.0, seed=train_seed,
                               progress=False, threads=args.threads, device=args.device,
                               batch_size=args.batch_size, lr=args.lr)
        train(run, "ekdun", kernels, subset, args.preset, {"schedule": schedule}, options,
              resume=ckpt.is_file())
    model, _ = network_from_checkpoint(ckpt)
    model.eval()
    test_set = PairsDataset(data / "test")
    images, truth = [], []
    with torch.no_grad():
        for i in range(len(test_set)):
            x, y = test_set[i]
            images.append(model(y[None])[0].numpy())
            truth.append(x.numpy())
    return _scores(images, truth)


def _mean_std(values: list[float]) -> str:
    a = np.asarray(values)
    return f"{a.mean():.2f}" + (f" ± {a.std(ddof=1):.2f}" if len(a) > 1 else "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/absorb")
    ap.add_argument("--sensor", type=int, nargs=2, default=(64, 64))
    ap.add_argument("--half-fov", default="30", help="comma list of half fields of view (°)")
    ap.add_argument("--n-train", default=None,
                    help="comma list of training-pair counts (default 96, or all of --data)")
    ap.add_argument("--data", type=Path, default=None,
                    help="an existing virtual-bench dataset (with its oracle) instead of "
                         "making one per --half-fov")
    ap.add_argument("--n-test", type=int, default=24)
    ap.add_argument("--photons", type=float, default=2000.0)
    ap.add_argument("--schedule", default="last-2", help="EK-DUN schedule with the EK oracle")
    ap.add_argument("--learned", default="yes", choices=("yes", "none"),
                    help="'none': the classical columns only")
    ap.add_argument("--seeds", default="0", help="training seeds, e.g. 0,1,2")
    ap.add_argument("--physics", default="SI,EK",
                    help="which learned runs to train: SI (base only), EK or both; two "
                         "processes with one each share the cores")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--epochs", type=int, default=15)
    ap.add_argument("--batch-size", type=int, default=None)
    ap.add_argument("--lr", type=float, default=None)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tune", type=int, default=4, help="training pairs that choose the TV")
    ap.add_argument("--iterations", type=int, default=100, help="ADMM-TV iterations")
    ap.add_argument("--tv-grid", default=",".join(f"{t:g}" for t in TV_GRID),
                    help="comma list of TV weights the tuning pairs choose from")
    args = ap.parse_args(argv)
    args.tv_grid = tuple(float(t) for t in args.tv_grid.split(","))
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    if args.data is not None:
        manifest = read_manifest(args.data)
        if manifest is None:
            raise SystemExit(f"{args.data}: not a virtual-bench dataset (no manifest.json)")
        spec = VirtualBenchSpec.from_dict(manifest["spec"])
        fovs = [spec.half_fov_deg]
        args.sensor, args.photons, args.n_test = spec.sensor_shape, spec.photons, spec.n_test
        n_train = args.n_train or str(spec.n_train)
    else:
        fovs = [float(f) for f in args.half_fov.split(",")]
        n_train = args.n_train or "96"
    counts = sorted(int(n) for n in n_train.split(","))
    rows = []
    for fov in fovs:
        data = args.data if args.data is not None else dataset(out, fov, counts[-1], args)
        files = oracles(data, out)
        t0 = time.perf_counter()
        cl = {name: classical_cached(out, name, files[key], data, args)
              for name, key in (("SI", "si"), ("EK", "ek"))}
        print(f"FOV ±{fov:g}°: classical SI {cl['SI']['psnr']:.2f} dB (tv {cl['SI']['tv']:g}),"
              f" EK {cl['EK']['psnr']:.2f} dB (tv {cl['EK']['tv']:g}) "
              f"[{time.perf_counter() - t0:.0f} s]", flush=True)
        for n in counts if args.learned == "yes" else [counts[-1]]:
            row: dict[str, Any] = {"half_fov": fov, "n_train": n, "classical": cl,
                                   "learned": {}}
            if args.learned == "yes":
                for name, key, schedule in (("SI", "si_as_paper", "base"),
                                            ("EK", "ek", args.schedule)):
                    if name not in args.physics.split(","):
                        continue
                    row["learned"][name] = []
                    for s in seeds:
                        run = out / "runs" / f"fov{fov:g}-n{n}-{name}-{schedule}-t{s}"
                        t0 = time.perf_counter()
                        score = learned(run, files[key], schedule, data, n, args, s)
                        row["learned"][name].append({"seed": s, **score})
                        print(f"  N {n}, {name} ({schedule}, frozen), seed {s}: "
                              f"{score['psnr']:.2f} dB [{time.perf_counter() - t0:.0f} s]",
                              flush=True)
            rows.append(row)
    write_json(out / "results.json", rows)
    print()
    print(f"{args.sensor[0]}x{args.sensor[1]}, photons {args.photons:g}, {args.n_test} test "
          f"pairs; learned: preset {args.preset}, {args.epochs} epochs, seeds {args.seeds}, "
          f"kernels frozen; EK-DUN with the EK oracle: {args.schedule}")
    print("| half FOV | N train | classical SI / EK (dB) | classical gain | learned SI / EK "
          "(dB) | learned gain (paired) | absorbed | = SI corrected + EK shortfall |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        c = r["classical"]
        c_gain = c["EK"]["psnr"] - c["SI"]["psnr"]
        paired = sorted({e["seed"] for e in r["learned"].get("SI", [])}
                        & {e["seed"] for e in r["learned"].get("EK", [])})
        if paired:
            by_seed = {name: {e["seed"]: e["psnr"] for e in r["learned"][name]}
                       for name in ("SI", "EK")}
            si = [by_seed["SI"][t] for t in paired]
            ek = [by_seed["EK"][t] for t in paired]
            gains = [b - a for a, b in zip(si, ek, strict=True)]
            gain = _mean_std(gains)
            learned_cells = (f"{_mean_std(si)} / {_mean_std(ek)} | "
                             f"{'+' if np.mean(gains) >= 0 else ''}{gain} | ")
            if c_gain > 0:
                corrected = (np.mean(si) - c["SI"]["psnr"]) / c_gain
                shortfall = (c["EK"]["psnr"] - np.mean(ek)) / c_gain
                learned_cells += (f"{1 - np.mean(gains) / c_gain:.0%} | {corrected:.0%} + "
                                  f"{shortfall:.0%}")
            else:
                learned_cells += "n/a | n/a"
        else:
            learned_cells = "- | - | - | -"
        print(f"| ±{r['half_fov']:g}° | {r['n_train']} | {c['SI']['psnr']:.2f} / "
              f"{c['EK']['psnr']:.2f} | {c_gain:+.2f} | {learned_cells} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
