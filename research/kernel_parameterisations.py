"""Fig. 7, the experiment: do EK-DUN's learned kernels find the measured modes and the oracle?

Free / physical / flow kernels, two seeds, any λ, against the measured modes and the oracle.

The one entry point of the Fig. 7 experiment at any scale. On a virtual-bench dataset (made
with ``--sensor``, ``--n-train``, ``--n-test``, ``--photons`` in ``OUT/dataset`` if absent, or an
existing one given by ``--data``), EK-DUN (``--schedule``, default last-2; ``--preset``, default
tiny) is trained (:func:`research.kernel_models.train`) with each kernel parameterisation
(``--params``), each physics weight (``--physics-weights``) and each training seed
(``--train-seeds``), seeded from the measured fit (``psfkit fit-eigen`` of the dataset's grid)
and from one PSF (``Kv = Kh = Kbase`` = the fit's ``Kbase``); on request also from the
pairs fits and from the operator oracle itself (``--seeds oracle``). For each run: test
PSNR/SSIM, the kernel-change split (pedestal fraction, gain, displacement) against the initial
kernels, the displacement-map correlation and difference NCC against the measured modes, the
principal angles to the top PCA modes (``research.compare``), and the same numbers against the
dataset's **operator oracle** of the run's convention (``DATA/oracle/paper_<c>.npz``, the best
eigen-kernel model of the simulator; difference NCC, displacement correlation and end-point
error of Kv / Kh, principal angles). Every run, seed and the oracle also get their prediction
error on the held-out test pairs (``psfkit eval-model``'s scaled mean): whether the learned
kernels are a better forward model than their seed, not only a better partner of the U-Net.
The seeds and the oracle itself are scored against the oracle as reference rows (the oracle
against itself: NCC 1). A ``--data`` without oracles (``python -m research.oracle DATA
--write-dataset`` writes them; a dataset this study makes gets them) gives a note and the
measured-only columns.

Runs are ``OUT/runs/<seed>-<param>-<schedule>-l<λ>-t<training seed>``; a finished run is
reused, an interrupted one resumed, one trained with other settings refused.
``OUT/results.json`` (runs, reference rows, the oracle) gets each run as soon as it is scored
and merges the runs of earlier invocations on the same folder, keyed on seed, kernels,
schedule, preset, λ, training seed and epochs (an interrupted invocation keeps its finished
runs); the folder is tied to its dataset (``OUT/experiment.json``). Prints the Markdown table
(``--table``: from ``results.json`` alone), with mean ± sd over training seeds and the PSNR
of each set-up paired with free pixels of the same seed, λ and training seed.

``--measure-lr`` instead reports, at the seed, the RMS of each kernel parameter group and of
its gradient over a few batches next to the network's, and the relative size of one Adam step
(``lr / RMS(parameter)``) each learning rate gives: the measurement behind
``LR_MULTIPLIER``.

Usage::

    python -m research.kernel_parameterisations --out runs/kparam [--epochs 15]
    python -m research.kernel_parameterisations --out runs/f7-128 --sensor 128 128 \
        --n-train 800 --photons 20000 --physics-weights 0,1 --train-seeds 0,1,2 \
        --preset paper --batch-size 8 --lr 5e-4 --device cuda
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ekdun.data.pairs import PairsDataset
from ekdun.data.virtual_bench import (
    VirtualBenchSpec,
    make_virtual_bench,
    read_manifest,
)
from ekdun.device import (
    AMP_CHOICES,
    resolve_amp,
    resolve_device,
)
from ekdun.evaluation.metrics import psnr, ssim
from ekdun.nets.builder import encode_overrides
from ekdun.nets.checkpoint import load_checkpoint
from ekdun.training import TrainOptions
from ekdun.training.trainer import CHECKPOINT, _param_groups
from psfkit.cli.main import run_cli
from psfkit.errors import InvalidInputError
from psfkit.fitting.pairs.fit import fit_pairs, predict, relative_errors
from psfkit.fitting.pairs.options import PairFitOptions
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.io import read_grid, read_pairs
from psfkit.io.jsonable import write_json
from research._kparam_table import as_document, format_number, markdown_table, run_key
from research.benchmark_tiny import fit_seed_kernels
from research.compare import compare_kernels, measure_modes
from research.compare.options import CompareOptions
from research.kernel_models import (
    LR_MULTIPLIER,
    build_network,
    network_from_checkpoint,
    recorded,
    seed_support,
    train,
)
from research.oracles import oracle_file, write_dataset_oracles

PARAMS = ("free", "physical", "flow")
#: Model overrides of each run name (``--params``); ``physical-gain`` is not in the default set.
OVERRIDES = {"free": {"kernel_param": "free"}, "physical": {"kernel_param": "physical"},
             "flow": {"kernel_param": "flow"},
             "physical-gain": {"kernel_param": "physical", "kernel_gain": True}}
SEEDS = ("measured", "one-psf")
#: Every start ``--seeds`` accepts: the default two, and the pairs fits (``psfkit fit-pairs`` of
#: the training pairs, made only when asked for: each costs minutes at 128²): ``pairs`` with
#: fit-pairs' defaults (non-negative kernels), ``pairs-free`` with ``--no-nonneg`` (the
#: unconstrained least-squares fit: the one that converges to the operator oracle, which is
#: unconstrained too).
PAIRS_SEEDS = {"pairs": True, "pairs-free": False}     # name -> non-negative
#: ``oracle``: the dataset's operator oracle itself as the start (NCC 1): whether training
#: keeps kernels that start at the oracle near it (the measured-seed target's limit case).
ORACLE_SEED = "oracle"
ALL_SEEDS = (*SEEDS, *PAIRS_SEEDS, ORACLE_SEED)
SEED_NAMES = {"measured": "measured fit (seed)", "one-psf": "one PSF (seed)",
              "pairs": "pairs fit (seed)", "pairs-free": "unconstrained pairs fit (seed)"}
#: Dataset options and the VirtualBenchSpec fields they set.
DATASET_OPTIONS = {"sensor_shape": "--sensor", "n_train": "--n-train", "n_test": "--n-test",
                   "photons": "--photons"}
EXPERIMENT = "experiment.json"


def dataset(args: argparse.Namespace, out: Path) -> Path:
    """The virtual-bench dataset: ``--data`` (or ``OUT/dataset``) as it is when it holds one,
    else made there with the dataset options.

    Raises
    ------
    InvalidInputError
        A dataset option disagrees with the existing dataset, or the folder holds something
        else.
    """
    root = Path(args.data) if args.data else out / "dataset"
    given = {"sensor_shape": None if args.sensor is None else list(args.sensor),
             "n_train": args.n_train, "n_test": args.n_test, "photons": args.photons}
    given = {k: v for k, v in given.items() if v is not None}
    manifest = read_manifest(root)
    if manifest is not None:
        spec = manifest["spec"]
        for key, value in given.items():
            have = spec.get(key)
            same = (list(have) == value) if key == "sensor_shape" else float(have) == value
            if not same:
                raise InvalidInputError(
                    f"{root}: the dataset was made with {DATASET_OPTIONS[key]} "
                    f"{' '.join(map(str, have)) if key == 'sensor_shape' else have}, not "
                    f"{' '.join(map(str, value)) if key == 'sensor_shape' else value}; leave "
                    "the option out to reuse it, or give another --data")
        return root
    if root.is_dir() and any(root.iterdir()):
        raise InvalidInputError(f"{root}: exists and is not a virtual-bench dataset (no "
                                "manifest.json); give a dataset or a new folder")
    values = {k: (tuple(v) if k == "sensor_shape" else v) for k, v in given.items()}
    spec = VirtualBenchSpec(**values)
    print(f"making the dataset {root} ({spec.sensor_shape[0]}x{spec.sensor_shape[1]}, "
          f"{spec.n_train} train / {spec.n_test} test pairs, photons {spec.photons:g})",
          flush=True)
    made = make_virtual_bench(root, spec, progress=False, device=resolve_device(args.device))
    write_dataset_oracles(made)      # what the runs are scored against
    return made


def tie_to_dataset(out: Path, data: Path) -> None:
    """Record which dataset ``out``'s seeds and runs belong to; refuse another one."""
    manifest = read_manifest(data)
    assert manifest is not None
    record = {"dataset": str(data.resolve()), "content_hash": manifest["content_hash"],
              "spec": manifest["spec"]}
    path = out / EXPERIMENT
    if path.is_file():
        old = json.loads(path.read_text(encoding="utf-8"))
        if old.get("content_hash") != record["content_hash"]:
            raise InvalidInputError(f"{out}: its seeds and runs were made on another dataset "
                                    f"({old.get('dataset')}); choose another --out")
        return
    fit = out / "kernels_fit.npz"
    if fit.is_file() and tuple(load_kernels(fit).sensor_shape) != tuple(
            manifest["spec"]["sensor_shape"]):
        raise InvalidInputError(f"{fit}: fitted on a {load_kernels(fit).sensor_shape} dataset, "
                                f"not this one; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    write_json(path, record)


def prepare(out: Path, data: Path, pairs: tuple[str, ...] = (),
            oracle: bool = False) -> dict[str, Path]:
    """The measured fit and the one-PSF seed of ``data`` (cached in ``out``), each pairs
    fit of :data:`PAIRS_SEEDS` that ``pairs`` names or an earlier invocation made, and with
    ``oracle`` the dataset's operator oracle (the file itself, not a copy).

    Raises
    ------
    InvalidInputError
        ``oracle`` and the dataset has no operator oracle matching the measured fit.
    """
    fit = out / "kernels_fit.npz"
    if not fit.is_file():
        fit_seed_kernels(data, fit)
    one = out / "kernels_one_psf.npz"
    if not one.is_file():
        model = load_kernels(fit)
        kernels = np.repeat(model.kernels[:1], len(model.kernels), axis=0)
        save_kernels(one, replace(model, kernels=kernels))
    seeds = {"measured": fit, "one-psf": one}
    for name, nonneg in PAIRS_SEEDS.items():
        fitted = out / f"kernels_{name.replace('-', '_')}.npz"
        if name in pairs and not fitted.is_file():
            fit_pairs_seed(data, fitted, load_kernels(fit), nonneg)
        if fitted.is_file():         # made once, then a reference row of every invocation
            seeds[name] = fitted
    if oracle:
        model, path, note = find_oracle(data, load_kernels(fit))
        if model is None or path is None:
            raise InvalidInputError(f"--seeds oracle: {note}")
        seeds[ORACLE_SEED] = path
    return seeds


def fit_pairs_seed(data: Path, out: Path, like: KernelModel, nonneg: bool = True) -> Path:
    """``psfkit fit-pairs`` of ``data``'s training pairs (its defaults; ``nonneg=False``:
    ``--no-nonneg``), in the basis and convention of the measured fit ``like``: the seed
    measured from pairs instead of the grid (issue 23: at 128² it is nearer the operator
    oracle than the grid fit can be)."""
    pairs = read_pairs(data / "train", check_pixels=False)
    scenes, measurements = pairs.load_all()
    print(f"fitting the pairs seed to {len(scenes)} training pairs (psfkit fit-pairs"
          f"{'' if nonneg else ' --no-nonneg'})", flush=True)
    options = PairFitOptions(basis=like.basis, convention=like.convention, nonneg=nonneg)
    fit = fit_pairs(scenes, measurements, options, progress=True)
    # the provenance the command line records, so the seed reads like its kernel file
    provenance = {"source": "psfkit fit-pairs", "pairs": str(pairs.root),
                  "names": list(pairs.names), "downsample": 1, "options": options.__dict__,
                  "training_error": [round(float(e), 6) for e in fit.training_error],
                  "physics": fit.physics()}
    return save_kernels(out, fit.kernel_model(provenance, pairs.read_options(1)))


def find_oracle(data: Path, seed: KernelModel) -> tuple[KernelModel | None, Path | None, str]:
    """The dataset's operator oracle of the seeds' convention, or a note why there is none."""
    path = oracle_file(data, seed.convention)
    if path is None:
        return None, None, (f"the dataset {data} has no {seed.convention}-side operator oracle "
                            f"(python -m research.oracle {data} --write-dataset writes it): "
                            "measured-only columns")
    oracle = load_kernels(path)
    if oracle.basis != seed.basis or tuple(oracle.sensor_shape) != tuple(seed.sensor_shape):
        return None, None, (f"{path}: basis {oracle.basis}, sensor {oracle.sensor_shape} do "
                            f"not match the seeds' ({seed.basis}, {seed.sensor_shape}): "
                            "measured-only columns")
    return oracle, path, f"operator oracle {path} ({seed.convention} side)"


def vs_oracle(model: KernelModel | Path, oracle: KernelModel) -> dict[str, Any]:
    """Difference NCC, displacement correlation and end-point error of Kv / Kh, and principal
    angles, of ``model`` against ``oracle`` (the reference), as ``oracle_*`` keys."""
    numbers = compare_kernels(model, oracle).learned.numbers()
    return {f"oracle_{'angles' if k == 'angles_deg' else k}": v for k, v in numbers.items()}


def prediction_error(model: KernelModel | Path, test: tuple[np.ndarray, np.ndarray]) -> float:
    """Mean ``‖y − s·A x‖ / ‖y‖`` of a kernel file over the held-out ``test`` pairs
    ``(scenes, measurements)``, with the best scale ``s`` per pair (``psfkit eval-model``'s
    "scaled" mean).

    Whether learned kernels are a better forward model than their seed: the reconstruction
    loss alone can raise PSNR while the kernels predict the measurements worse (issue 24).
    """
    kernels = load_kernels(model) if isinstance(model, Path) else model
    scenes, measurements = test
    return float(relative_errors(predict(kernels, scenes), measurements)["scaled"].mean())


def reference_rows(seeds: dict[str, Path], oracle: KernelModel,
                   test: tuple[np.ndarray, np.ndarray]) -> list[dict[str, Any]]:
    """The seeds and the oracle itself against the oracle (the oracle: NCC 1, angles 0), each
    with its prediction error on the ``test`` pairs."""
    rows = [{"reference": SEED_NAMES.get(k, k), "file": str(p), **vs_oracle(p, oracle),
             "test_prediction_error": prediction_error(p, test)} for k, p in seeds.items()
            if k != ORACLE_SEED]           # the oracle seed is the row "the oracle itself"
    rows.append({"reference": "the oracle itself", "file": None, **vs_oracle(oracle, oracle),
                 "test_prediction_error": prediction_error(oracle, test)})
    return rows


def test_scores(model: torch.nn.Module, data: Path, device: torch.device | str = "cpu"
                ) -> dict[str, float]:
    """Mean PSNR / SSIM over the held-out test pairs (eval mode, batch 1)."""
    model = model.to(device).eval()
    test = PairsDataset(data / "test")
    p, s = [], []
    with torch.no_grad():
        for i in range(len(test)):
            x, y = test[i]
            out = model(y[None].to(device)).clamp(0, 1)
            p.append(float(psnr(out, x[None].to(device)).mean()))
            s.append(float(ssim(out, x[None].to(device)).mean()))
    return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s))}


def kernel_numbers(run: Path, modes: Any) -> dict[str, Any]:
    """research.compare of a run's learned kernels (with its initial kernels)."""
    cmp = compare_kernels(run / "kernels_learned.npz", modes,
                          initial=run / "kernels_initial.npz")
    doc = cmp.to_dict()
    row: dict[str, Any] = {}
    for name in ("v", "h"):
        m = doc["learned"]["metrics"][name]
        row[f"{name}_disp_corr"] = m["vs_measured_kernels"]["corr"]
        row[f"{name}_diff_ncc"] = m["difference_ncc"]
        split = doc["kernel_change"]["learned_vs_initial"][name]
        row[f"{name}_gain"] = split["gain"]
        row[f"{name}_fractions"] = split["fractions"]
    change = doc["kernel_change"]["learned_vs_initial"]["all"]
    row["pedestal_share"] = change["pedestal_share_of_change"]
    row["outside_mass"] = change["outside_mass_fraction"]
    row["base_fractions"] = doc["kernel_change"]["learned_vs_initial"]["base"]["fractions"]
    row["angles_pca"] = doc["learned"]["principal_angles_deg_vs_measured_pca"]
    row["angles_eigen"] = doc["learned"]["principal_angles_deg_vs_measured_eigen"]
    row["compare"] = doc
    return row


def run_name(seed: str, param: str, schedule: str, weight: float, train_seed: int) -> str:
    """``OUT/runs/`` folder of one run: every setting that varies within an experiment."""
    return f"{seed}-{param}-{schedule}-l{weight:g}-t{train_seed}"


def check_reusable(ckpt: Path, expected: dict[str, Any]) -> dict[str, Any]:
    """The metadata of a run's checkpoint, refused when it was trained otherwise."""
    meta = load_checkpoint(ckpt)["metadata"]
    cfg = meta.get("training", {})
    overrides, weight = recorded(meta)
    have = {"preset": meta.get("preset"), "overrides": overrides,
            "seed": meta.get("seed"), "batch_size": cfg.get("batch_size"),
            "lr": cfg.get("lr"), "physics_weight": weight}
    for key, value in expected.items():
        if have[key] != value:
            raise InvalidInputError(f"{ckpt.parent}: trained with {key} {have[key]!r}, not "
                                    f"{value!r}; choose another --out (or remove the run)")
    return meta


def run_setup(out: Path, seed: str, param: str, weight: float, train_seed: int,
              args: argparse.Namespace) -> tuple[Path, dict[str, Any], TrainOptions,
                                                 dict[str, Any]]:
    """``(run folder, model overrides, train options, what a reusable checkpoint holds)``."""
    overrides = {**OVERRIDES[param], "schedule": args.schedule}
    options = TrainOptions(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                           seed=train_seed, amp=args.amp,
                           device=args.device, progress=False, threads=args.threads)
    cfg = options.resolve(args.preset)
    run = out / "runs" / run_name(seed, param, args.schedule, weight, train_seed)
    expected = {"preset": args.preset, "overrides": encode_overrides(overrides),
                "seed": train_seed, "batch_size": cfg.batch_size, "lr": cfg.lr,
                "physics_weight": float(weight)}
    return run, overrides, options, expected


def train_one(out: Path, data: Path, seed_file: Path, seed: str, param: str, weight: float,
              train_seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """Train (or reuse, or resume) one run; returns its row without the kernel numbers."""
    run, overrides, options, expected = run_setup(out, seed, param, weight, train_seed, args)
    ckpt = run / CHECKPOINT
    meta = check_reusable(ckpt, expected) if ckpt.is_file() else None
    if meta is None or meta["epoch"] < args.epochs:
        # the benchmark's own folder: a run killed before its first checkpoint restarts
        train(run, "ekdun", seed_file, PairsDataset(data / "train"), args.preset, overrides,
              options, physics_weight=weight, resume=meta is not None, overwrite=meta is None)
        meta = load_checkpoint(ckpt)["metadata"]
    history = meta["history"]
    cfg = options.resolve(args.preset)
    return {"seed": seed, "param": param, "schedule": args.schedule, "preset": args.preset,
            "physics_weight": float(weight), "train_seed": train_seed,
            "epochs": meta["epoch"], "batch_size": cfg.batch_size, "lr": cfg.lr,
            "precision": meta.get("precision"), "run": str(run),
            "train_s": round(sum(h["seconds"] for h in history), 1),
            "final_train_loss": history[-1]["train_loss"],
            "final_physics_loss": (history[-1]["extra_loss"] / weight
                                   if "extra_loss" in history[-1] else
                                   history[-1].get("physics_loss"))}


def measure_lr(data: Path, seeds: dict[str, Path], batches: int = 6) -> list[dict[str, Any]]:
    """Gradient and parameter scale per group at the measured seed (see module docstring)."""
    train_set = PairsDataset(data / "train")
    lr, scale = 2e-3, 1e-2                     # tiny preset: network lr, kernel_lr_scale
    rows = []
    for param in PARAMS:
        torch.manual_seed(0)
        model = build_network("ekdun", load_kernels(seeds["measured"]), "tiny",
                              {"kernel_param": param})
        groups = _param_groups(model, lr, scale)
        grads: list[list[float]] = [[] for _ in groups]
        per_kernel = []
        for b in range(batches):
            x, y = zip(*(train_set[4 * b + i] for i in range(4)), strict=True)
            model.zero_grad()
            loss = torch.nn.functional.mse_loss(model(torch.stack(y)), torch.stack(x))
            loss.backward()
            if param == "free":
                g = model.physics.kernels.grad.detach()
                inside = seed_support(model.physics.kernels)
                per_kernel.append(torch.cat([
                    g.pow(2).mean(dim=(1, 2, 3)).sqrt(),
                    g[..., inside].pow(2).mean().sqrt()[None],
                    g[..., ~inside].pow(2).mean().sqrt()[None]]))
            for g, group in enumerate(groups):
                flat = torch.cat([p.grad.flatten() for p in group["params"]
                                  if p.grad is not None])
                grads[g].append(float(flat.pow(2).mean().sqrt()))
        for g, group in enumerate(groups):
            values = torch.cat([p.detach().flatten() for p in group["params"]])
            # logits are only defined on the support; fields/gains start at 0 (use 1 px)
            rms = float(values[torch.isfinite(values)].pow(2).mean().sqrt())
            name = "network" if g == 0 else f"kernels ({param})"
            rows.append({"group": name, "param_rms": rms, "grad_rms": float(np.mean(grads[g])),
                         "lr": group["lr"],
                         "relative_step": group["lr"] / max(rms, 1e-12)})
        if per_kernel:
            # how strongly the loss constrains each kernel: RMS gradient per pixel of Kbase,
            # Kv, Kh (the last-2 schedule only uses Kv, Kh in 2 of 10 iterations)
            rows.append({"group": "free pixels: grad RMS per pixel of Kbase, Kv, Kh; inside, "
                                  "outside the caustic support",
                         "per_kernel_grad_rms": torch.stack(per_kernel).mean(0).tolist()})
    return rows


def _floats(text: str, flag: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InvalidInputError(f"{flag}: expected a comma-separated list of numbers, got "
                                f"{text!r}") from None
    if not values or not all(np.isfinite(v) and v >= 0 for v in values):
        raise InvalidInputError(f"{flag}: expected finite numbers >= 0, got {text!r}")
    return values


def _ints(text: str, flag: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InvalidInputError(f"{flag}: expected a comma-separated list of integers, got "
                                f"{text!r}") from None
    if not values or min(values) < 0:
        raise InvalidInputError(f"{flag}: expected integers >= 0, got {text!r}")
    return values


def _names(text: str, flag: str, allowed: tuple[str, ...] | dict) -> list[str]:
    names = [v.strip() for v in text.split(",") if v.strip()]
    bad = [n for n in names if n not in allowed]
    if not names or bad:
        raise InvalidInputError(f"{flag}: {', '.join(bad) or 'nothing given'} not among "
                                f"{', '.join(allowed)}")
    return names


def experiment(args: argparse.Namespace) -> int:
    """The body of the command (see the module docstring)."""
    out = Path(args.out)
    if args.table:
        path = out / "results.json"
        if not path.is_file():
            raise InvalidInputError(f"{path}: no results yet (run the experiment first)")
        print(markdown_table(json.loads(path.read_text(encoding="utf-8"))))
        return 0
    seeds_run = _names(args.seeds, "--seeds", ALL_SEEDS)
    params = _names(args.params, "--params", OVERRIDES)
    weights = _floats(args.physics_weights, "--physics-weights")
    train_seeds = _ints(args.train_seeds, "--train-seeds")
    if args.threads < 1:
        raise InvalidInputError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    resolve_amp(args.amp, device)                # refused here, not after the dataset
    data = dataset(args, out)
    tie_to_dataset(out, data)
    seeds = prepare(out, data, pairs=tuple(s for s in seeds_run if s in PAIRS_SEEDS),
                    oracle=ORACLE_SEED in seeds_run)
    if args.measure_lr:
        rows = measure_lr(data, seeds)
        for r in rows:
            if "per_kernel_grad_rms" in r:
                print(r["group"], ", ".join(f"{v:.3g}" for v in r["per_kernel_grad_rms"]))
                continue
            print(f"{r['group']:22s} param RMS {r['param_rms']:.3g}  grad RMS "
                  f"{r['grad_rms']:.3g}  lr {r['lr']:.3g}  lr/RMS {r['relative_step']:.3g}")
        write_json(out / "lr_measurement.json", rows)
        return 0
    plan = list(itertools.product(seeds_run, params, weights, train_seeds))
    for seed, param, weight, train_seed in plan:
        # refuse a folder of runs trained otherwise before anything is trained
        run, _, _, expected = run_setup(out, seed, param, weight, train_seed, args)
        if (run / CHECKPOINT).is_file():
            check_reusable(run / CHECKPOINT, expected)
    measured = load_kernels(seeds["measured"])
    oracle, oracle_path, note = find_oracle(data, measured)
    print(f"oracle: {note}", flush=True)
    modes = measure_modes(read_grid(data / "grid"), measured.basis, measured.convention,
                          tuple(measured.sensor_shape), CompareOptions())
    # the test pairs, read once: every run and reference row is scored on them
    test = read_pairs(data / "test", check_pixels=False).load_all()
    references = [] if oracle is None else reference_rows(seeds, oracle, test)
    header = {"dataset": str(data), "spec": read_manifest(data)["spec"],  # type: ignore[index]
              "oracle": None if oracle is None else {"file": str(oracle_path), "kind": "operator",
                                                     "convention": oracle.convention},
              "oracle_note": note, "references": references}
    for seed, param, weight, train_seed in plan:
        row = train_one(out, data, seeds[seed], seed, param, weight, train_seed, args)
        run = Path(row["run"])
        model, _ = network_from_checkpoint(run / CHECKPOINT)
        row.update(test_scores(model, data, device))
        row.update(kernel_numbers(run, modes))
        row["test_prediction_error"] = prediction_error(run / "kernels_learned.npz", test)
        if oracle is not None:
            row.update(vs_oracle(run / "kernels_learned.npz", oracle))
        write_json(run / "numbers.json", row)
        record(out / "results.json", header, row)
        fn = format_number
        text = (f"{seed:8s} {param:8s} λ {weight:<5g} t{train_seed} PSNR {row['psnr']:.2f} "
                f"SSIM {row['ssim']:.4f} pedestal {row['pedestal_share']:.3f} outside "
                f"{row['outside_mass']:.3f} disp {fn(row['v_disp_corr'])} / "
                f"{fn(row['h_disp_corr'])} ncc {fn(row['v_diff_ncc'], '.3f')} / "
                f"{fn(row['h_diff_ncc'], '.3f')} prediction error "
                f"{row['test_prediction_error']:.4f}")
        if oracle is not None:
            text += (f" | oracle ncc {fn(row['oracle_v_diff_ncc'], '.3f')} / "
                     f"{fn(row['oracle_h_diff_ncc'], '.3f')} disp "
                     f"{fn(row['oracle_v_disp_corr'])} / {fn(row['oracle_h_disp_corr'])}")
        print(text, flush=True)
    print(markdown_table(json.loads((out / "results.json").read_text(encoding="utf-8"))))
    print(f"LR multipliers: {LR_MULTIPLIER}")
    return 0


@contextmanager
def exclusive(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path``.lock (POSIX ``flock``; where there is none, no lock)."""
    try:
        import fcntl
    except ImportError:                 # Windows: invocations on one folder must not overlap
        yield
        return
    with open(path.with_name(path.name + ".lock"), "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def record(path: Path, header: dict[str, Any], row: dict[str, Any]) -> None:
    """Merge one finished run into ``results.json`` at once (replacing its earlier row, keeping
    the runs of earlier or other invocations on the folder): an interrupted invocation loses
    no finished run, and the file is re-read for each run, not once per invocation. The
    read-merge-write holds a lock, so invocations running at once on one folder keep each
    other's rows."""
    summary = {k: v for k, v in row.items() if k != "compare"}
    key = run_key(summary)
    with exclusive(path):
        earlier = (as_document(json.loads(path.read_text(encoding="utf-8")))
                   if path.is_file() else {"runs": []})
        write_json(path, {**header, "runs": [r for r in earlier["runs"] if run_key(r) != key]
                          + [summary]})


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/kparam", help="experiment folder")
    data = ap.add_argument_group("dataset (virtual bench)")
    data.add_argument("--data", help="an existing virtual-bench dataset to reuse (made there "
                                     "with the options below if absent; default OUT/dataset)")
    data.add_argument("--sensor", type=int, nargs=2, metavar=("H", "W"),
                      help="sensor size of a new dataset (default 64 64)")
    data.add_argument("--n-train", type=int, help="training pairs of a new dataset (96)")
    data.add_argument("--n-test", type=int, help="held-out test pairs of a new dataset (24)")
    data.add_argument("--photons", type=float,
                      help="photo-electrons per unit measurement of a new dataset (2000)")
    runs = ap.add_argument_group("runs")
    runs.add_argument("--params", default=",".join(PARAMS),
                      help=f"kernel parameterisations, of {', '.join(OVERRIDES)}")
    runs.add_argument("--seeds", default=",".join(SEEDS),
                      help="starts: measured (the grid fit), one-psf, pairs (the pairs fit of "
                           "the training pairs), pairs-free (the same, --no-nonneg), oracle "
                           "(the dataset's operator oracle itself); the last three are not in "
                           "the default")
    runs.add_argument("--physics-weights", default="0",
                      help="physics weights λ (ekdun train --physics-weight), e.g. 0,1")
    runs.add_argument("--train-seeds", default="0",
                      help="training seeds (weights, batch order) of every set-up, e.g. 0,1,2: "
                           "the spread says which PSNR differences are resolved")
    runs.add_argument("--preset", default="tiny", help="EK-DUN preset (tiny, paper)")
    runs.add_argument("--schedule", default="last-2", choices=("last-2", "base", "all"),
                      help="where the eigen-kernel model is used")
    runs.add_argument("--epochs", type=int, default=15)
    runs.add_argument("--batch-size", type=int, help="global batch (default: the preset's)")
    runs.add_argument("--lr", type=float, help="learning rate (default: the preset's)")
    runs.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:N")
    runs.add_argument("--threads", type=int, default=1,
                      help="torch threads (1: fastest on a shared 2-core machine)")
    runs.add_argument("--amp", default="auto", choices=AMP_CHOICES,
                      help="autocast precision (auto: fp16 on CUDA, off on CPU)")
    ap.add_argument("--measure-lr", action="store_true",
                    help="measure parameter and gradient scales at the seed instead")
    ap.add_argument("--table", action="store_true", help="print OUT/results.json as Markdown")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the experiment; bad input is one line on stderr and exit status 2."""
    ap = parser()
    ap.set_defaults(func=experiment)
    return run_cli(Path(sys.argv[0]).name, ap, argv)


if __name__ == "__main__":
    raise SystemExit(main())
