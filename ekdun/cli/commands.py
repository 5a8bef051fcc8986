"""The ``ekdun`` sub-commands (each a thin wrapper over the library)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ekdun.errors import InvalidInputError
from ekdun.model_names import MODEL_NAMES


def _say(args: argparse.Namespace, text: str) -> None:
    if not getattr(args, "quiet", False):
        print(text, file=sys.stderr)


def _threads(args: argparse.Namespace) -> None:
    import torch

    if getattr(args, "threads", None):
        torch.set_num_threads(args.threads)


def resolve_split(data: str, split: str) -> Path:
    """See :func:`ekdun.data.virtual_bench.resolve_split`."""
    from ekdun.data.virtual_bench import resolve_split as resolve

    return resolve(data, split)


def register(sub: argparse._SubParsersAction) -> None:
    # ---------------------------------------------------------------- make-dataset
    p = sub.add_parser("make-dataset", help="build (or reuse) a cached virtual-bench dataset",
                       description="Simulate a PSF grid on the virtual bench, scenes (dead "
                                   "leaves + scikit-image natural images) and their "
                                   "measurements through a dense shift-variant model with "
                                   "sensor noise. Reused when the manifest matches.")
    p.add_argument("out", help="dataset folder")
    p.add_argument("--sensor", type=int, nargs=2, default=(64, 64), metavar=("H", "W"))
    p.add_argument("--n-train", type=int, default=96)
    p.add_argument("--n-test", type=int, default=24)
    p.add_argument("--grid", type=int, nargs=2, default=(9, 9), metavar=("N", "M"),
                   help="PSF grid (and dense-model nodes), default 9 9")
    p.add_argument("--half-fov", type=float, default=30.0,
                   help="field angle (deg) at the sensor edge (default 30)")
    p.add_argument("--aperture", type=float, default=1.3,
                   help="side of the square aperture in mm (default 1.3)")
    p.add_argument("--photons", type=float, default=2000.0,
                   help="photo-electrons per unit measurement (default 2000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run_make_dataset)

    # ---------------------------------------------------------------- train
    p = sub.add_parser("train", help="train EK-DUN, Le-ADMM-U or UPDN",
                       description="MSE, Adam, ExponentialLR per epoch; checkpoint every epoch "
                                   "(atomic); --resume continues exactly. Works under "
                                   "torchrun (DistributedDataParallel; --batch-size is the "
                                   "global batch).")
    p.add_argument("data", help="pairs folder, or a virtual-bench dataset (uses its train/)")
    p.add_argument("run_dir", help="output folder (checkpoint.pt, log.csv, kernel files)")
    p.add_argument("--model", choices=MODEL_NAMES, default="ekdun")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--kernels", help="kernel file (.npz, e.g. from psfkit fit-eigen)")
    src.add_argument("--psf", help="measured PSF image (same size as the measurements)")
    p.add_argument("--preset", choices=("tiny", "paper"), default="tiny")
    p.add_argument("--schedule", help="EK-DUN schedule: base, last-2 (last-N) or all")
    p.add_argument("--iterations", type=int, help="override the preset's iterations")
    p.add_argument("--epochs", type=int)
    p.add_argument("--batch-size", type=int, help="global batch size")
    p.add_argument("--lr", type=float)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto (cuda if present), cpu, cuda:0 ...")
    p.add_argument("--threads", type=int, help="torch CPU threads")
    p.add_argument("--no-amp", action="store_true", help="no mixed precision on CUDA")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/checkpoint.pt")
    p.add_argument("--overwrite", action="store_true", help="start RUN_DIR over")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run_train)

    # ---------------------------------------------------------------- eval
    p = sub.add_parser("eval", help="PSNR/SSIM/LPIPS, parameters, runtime, memory → tables",
                       description="Evaluate checkpoints on held-out pairs and write Table 1 "
                                   "(models) and Table 2 (EK-DUN schedules) as Markdown and "
                                   "JSON.")
    p.add_argument("checkpoints", nargs="+", help="checkpoint.pt files (or run folders)")
    p.add_argument("--data", required=True,
                   help="pairs folder, or a virtual-bench dataset (uses its test/)")
    p.add_argument("--out", required=True, help="folder for the tables")
    p.add_argument("--lpips-weights", help="local AlexNet weights for LPIPS "
                                           "(else $EKDUN_LPIPS_WEIGHTS; else unavailable)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run_eval)

    # ---------------------------------------------------------------- reconstruct
    p = sub.add_parser("reconstruct", help="reconstruct measurements with a checkpoint")
    p.add_argument("checkpoint")
    p.add_argument("measurements", nargs="+", help="image files (npy, png, tiff) or folders")
    p.add_argument("--out", required=True, help="output folder (NAME.npy + NAME.png)")
    p.add_argument("--channel-order", choices=("RGB", "BGR"), default="RGB")
    p.add_argument("--device", default="cpu")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=run_reconstruct)

    # ---------------------------------------------------------------- admm
    from ekdun.cli import classical_cmd

    classical_cmd.register(sub)

    # ---------------------------------------------------------------- export-kernels
    p = sub.add_parser("export-kernels", help="write a trained EK-DUN's kernels as a psfkit "
                                              "kernel file")
    p.add_argument("checkpoint")
    p.add_argument("--out", required=True, help="kernel file (.npz)")
    p.set_defaults(func=run_export_kernels)

    # ---------------------------------------------------------------- benchmark-tiny
    p = sub.add_parser("benchmark-tiny", help="dataset, fit, 5 trainings, Tables 1 and 2 "
                                              "(tiny preset, CPU)")
    p.add_argument("out", help="benchmark folder (resumable)")
    p.add_argument("--epochs", type=int)
    p.add_argument("--n-train", type=int, default=96)
    p.add_argument("--n-test", type=int, default=24)
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads (default 1: fastest on a shared 2-core machine)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the dataset (diffuser, scenes, noise) and of the trainings")
    p.add_argument("--lpips-weights")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run_benchmark_tiny)


def run_make_dataset(args: argparse.Namespace) -> int:
    from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench

    spec = VirtualBenchSpec(sensor_shape=tuple(args.sensor), n_train=args.n_train,
                            n_test=args.n_test, grid_shape=tuple(args.grid),
                            half_fov_deg=args.half_fov, aperture_mm=args.aperture,
                            photons=args.photons, seed=args.seed)
    root = make_virtual_bench(args.out, spec, progress=not args.quiet)
    _say(args, f"dataset: {root}")
    return 0


def run_train(args: argparse.Namespace) -> int:
    from ekdun.data.pairs import PairsDataset
    from ekdun.training import TrainOptions, train

    dataset = PairsDataset(resolve_split(args.data, "train"))
    overrides: dict[str, Any] = {}
    if args.schedule:
        if args.model != "ekdun":
            raise InvalidInputError("--schedule applies to --model ekdun only")
        overrides["schedule"] = args.schedule
    if args.iterations:
        overrides["iterations"] = args.iterations
    options = TrainOptions(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                           seed=args.seed, amp=not args.no_amp, device=args.device,
                           progress=not args.quiet, threads=args.threads)
    result = train(args.run_dir, args.model, args.kernels or args.psf, dataset, args.preset,
                   overrides, options, resume=args.resume, overwrite=args.overwrite)
    last = result["history"][-1] if result["history"] else {}
    _say(args, f"trained {args.model}: {len(result['history'])} epochs, final loss "
               f"{last.get('train_loss', float('nan')):.4g}; {args.run_dir}")
    return 0


def _checkpoint_path(item: str) -> Path:
    from ekdun.evaluation.evaluate import checkpoint_path

    return checkpoint_path(item)


def run_eval(args: argparse.Namespace) -> int:
    from ekdun.evaluation import LPIPSMetric, evaluate_checkpoints, write_tables

    _threads(args)
    lpips = LPIPSMetric(args.lpips_weights)
    if not lpips.available:
        _say(args, lpips.reason)
    results = evaluate_checkpoints(args.checkpoints, args.data, lpips, args.device,
                                   log=lambda line: _say(args, line))
    write_tables(args.out, results, [lpips.reason] if lpips.reason else [])
    return 0


def run_reconstruct(args: argparse.Namespace) -> int:
    from ekdun.reconstruction import reconstruct_files

    written = reconstruct_files(args.checkpoint, args.measurements, args.out,
                                args.channel_order, args.device, args.overwrite)
    print(f"{len(written)} reconstruction(s) in {args.out}", file=sys.stderr)
    return 0


def run_export_kernels(args: argparse.Namespace) -> int:
    from ekdun.training import export_kernels
    from psfkit.kernelfile import save_kernels

    out = Path(args.out)
    if out.suffix != ".npz":
        raise InvalidInputError(f"{out}: kernel files are .npz")
    save_kernels(out, export_kernels(_checkpoint_path(args.checkpoint)))
    print(f"learned kernels: {out}", file=sys.stderr)
    return 0


def run_benchmark_tiny(args: argparse.Namespace) -> int:
    import torch

    from ekdun.benchmark import run_tiny_benchmark
    from ekdun.data.virtual_bench import VirtualBenchSpec
    from ekdun.training import TrainOptions

    torch.set_num_threads(args.threads)
    spec = VirtualBenchSpec(n_train=args.n_train, n_test=args.n_test, seed=args.seed)
    options = TrainOptions(epochs=args.epochs, progress=not args.quiet, threads=args.threads,
                           seed=args.seed)
    result = run_tiny_benchmark(args.out, spec, options, lpips_weights=args.lpips_weights,
                                progress=not args.quiet,
                                log=lambda s: _say(args, s))
    _say(args, json.dumps(result["timings"]))
    return 0
