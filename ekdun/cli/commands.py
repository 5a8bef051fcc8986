"""The ``ekdun`` sub-commands (each a thin wrapper over the library)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from ekdun.cli.vocabulary import add_flag, set_threads
from ekdun.errors import InvalidInputError
from ekdun.flag_ranges import flag
from psfkit.cli.help_all import add_help_all, mark_advanced
from psfkit.cli.main import register_moved
from psfkit.cli.run_file import add_config_option, run_file_record
from psfkit.cli.vocabulary import NOTICES, add_retired
from psfkit.io.validation import MAX_GRID_SIDE, bounded_size


def _say(args: argparse.Namespace, text: str) -> None:
    if not getattr(args, "quiet", False):
        print(text, file=sys.stderr)


#: Commands that left the user CLI for the source repository's research/ folder
#: (docs/migration.md): the replacement of each. The old spelling is kept, hidden, for one
#: release: it cannot run the study (research/ is not installed), so it says where it went.
MOVED = {"oracle": "python -m research.oracle",
         "benchmark-tiny": "python -m research.benchmark_tiny"}


#: The note of ``ekdun export-kernels`` (deprecated, hidden; docs/migration.md).
EXPORT_KERNELS_NOTE = (
    "note: `ekdun export-kernels` is deprecated: `ekdun train` writes the learned kernels as "
    "RUN/kernels_learned.npz after every epoch; this command stays for one release for "
    "checkpoints of older runs (docs/migration.md)")


#: ``ekdun train`` flags that moved to research/ (issue 44): given, train fails saying where.
MOVED_TRAIN_FLAGS = {"--kernel-param": "research/kernel_models.py",
                     "--physics-weight": "research/physics_loss.py"}


#: Flags that no longer do anything, kept hidden for one release (docs/migration.md):
#: ``(command, flag) -> (nargs, note, choices)`` (the shape of psfkit's ``RETIRED``). Each
#: prints its note after the work and is otherwise ignored (a value is still checked).
RETIRED_FLAGS = {
    ("make-dataset", "--no-oracle"): (
        0, "note: --no-oracle is deprecated and ignored: make-dataset no longer writes the "
           "eigen-kernel oracles (python -m research.oracle DATASET --write-dataset does)", None),
    ("make-dataset", "--oracle-scenes"): (
        1, "note: --oracle-scenes is deprecated and ignored: make-dataset no longer writes the "
           "eigen-kernel oracles (python -m research.oracle DATASET --write-dataset "
           "--oracle-scenes N does)", None),
}


#: Flags that only ``--help-all`` lists: the bench's optics and noise, threads.
MAKE_DATASET_ADVANCED = ("--half-fov", "--aperture", "--photons", "--grid-frames", "--threads")
#: ... for train: what the pairs and kernel file decide (binning, channel order), the preset's
#: schedule overrides, the kernel learning rate, speed settings and --quiet (a training run
#: is watched; its log.csv records every epoch either way).
TRAIN_ADVANCED = ("--downsample", "--channel-order", "--schedule", "--iterations",
                  "--batch-size", "--lr", "--kernel-lr-scale", "--seed", "--threads", "--amp",
                  "--no-amp", "--channels-last", "--compile", "--loader-workers", "--quiet")
#: ... for eval: what each checkpoint records (channel order), threads.
EVAL_ADVANCED = ("--channel-order", "--threads")


def register(sub: argparse._SubParsersAction) -> None:
    # ---------------------------------------------------------------- make-dataset
    p = sub.add_parser("make-dataset", help="build (or reuse) a cached virtual-bench dataset",
                       description="Simulate a PSF grid on the virtual bench, scenes (dead "
                                   "leaves + scikit-image natural images) and their "
                                   "measurements through a dense shift-variant model with "
                                   "sensor noise. Reused when the manifest matches.")
    add_help_all(p)
    p.add_argument("out", help="dataset folder")
    p.add_argument("--sensor", type=flag("--sensor"), nargs=2, default=(64, 64), metavar=("H", "W"),
                   help="sensor size in pixels (default 64 64)")
    p.add_argument("--n-train", type=flag("--n-train"), default=96,
                   help="training scenes (default 96)")
    p.add_argument("--n-test", type=flag("--n-test"), default=24, help="test scenes (default 24)")
    p.add_argument("--grid", type=flag("--grid"), nargs=2, default=(9, 9), metavar=("N", "M"),
                   help="PSF grid (and dense-model nodes), default 9 9")
    p.add_argument("--half-fov", type=flag("--half-fov"), default=30.0,
                   help="field angle (deg) at the sensor edge (default 30)")
    p.add_argument("--aperture", type=flag("--aperture"), default=1.3,
                   help="side of the square aperture in mm (default 1.3)")
    p.add_argument("--photons", type=flag("--photons"), default=2000.0,
                   help="photo-electrons per unit measurement (default 2000)")
    p.add_argument("--grid-frames", type=flag("--grid-frames"), default=1, metavar="N",
                   help="frames averaged at each position of the PSF grid: its noise falls as "
                        "1/sqrt(N), as when a lab averages repeated captures (default 1: one "
                        "raw 12-bit frame; the pairs are unchanged)")
    add_flag(p, "--seed", "make-dataset", help="seed of the PSF noise, scenes and measurement "
                                                 "noise: the same seed, the same dataset "
                                                 "(default 0)")
    add_flag(p, "--device", "make-dataset",
             note="auto; where the noise-free measurements are computed, in float64 on any "
                  "device; the noise is drawn on the CPU")
    add_flag(p, "--threads", "make-dataset",
             help="processes drawing the scenes; the dataset is the same for any N (default: "
                  "the CPUs available, at most 16 and one per 64 scenes)")
    add_retired(p, "make-dataset", RETIRED_FLAGS, flag)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    mark_advanced(p, MAKE_DATASET_ADVANCED)
    p.set_defaults(func=run_make_dataset)

    # ---------------------------------------------------------------- train
    p = sub.add_parser("train", help="train EK-DUN, Le-ADMM-U or UPDN",
                       description="MSE, Adam, ExponentialLR per epoch; checkpoint every epoch "
                                   "(atomic); --resume continues exactly. Works under "
                                   "torchrun (DistributedDataParallel; --batch-size is the "
                                   "global batch). EK-DUN runs also write their kernels as psfkit "
                                   "kernel files: RUN_DIR/kernels_initial.npz (the seed) and "
                                   "kernels_learned.npz (every epoch).")
    add_help_all(p)
    p.add_argument("data", help="pairs folder, or a virtual-bench dataset (uses its train/)")
    p.add_argument("run_dir", help="output folder (checkpoint.pt, log.csv, kernel files)")
    add_flag(p, "--network", "train")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--kernels", help="kernel file (.npz, e.g. from psfkit fit-eigen)")
    src.add_argument("--psf", help="measured PSF image (same size as the measurements)")
    add_flag(p, "--holdout", "train", action="append",
             help="pairs (file stems, e.g. im65; comma-separated, repeatable) left out of "
                  "training and recorded in the checkpoint, so that eval scores only them "
                  "(default: none)")
    p.add_argument("--downsample", type=flag("--downsample"), metavar="N",
                   help="bin the pairs N x N (default: 1 if they have the kernels' size, else "
                        "the factor the kernel file was fitted with)")
    add_flag(p, "--channel-order", "train",
             note="the folder's (pairs.json; BGR for the DLMD layout lensed/ + diffuser/), "
                  "else the kernel file's record, else RGB")
    p.add_argument("--preset", choices=("tiny", "paper"), default="tiny",
                   help="network size and training schedule (default tiny)")
    p.add_argument("--schedule", help="EK-DUN schedule: base, last-2 (last-N) or all")
    p.add_argument("--iterations", type=flag("--iterations", "train"),
                   help="override the preset's iterations")
    p.add_argument("--epochs", type=flag("--epochs"), help="override the preset's epochs")
    p.add_argument("--batch-size", type=flag("--batch-size"), help="global batch size")
    p.add_argument("--lr", type=flag("--lr"), help="override the preset's learning rate")
    p.add_argument("--kernel-lr-scale", type=flag("--kernel-lr-scale"), metavar="SCALE",
                   help="EK-DUN: learning rate of the physics kernels = SCALE x --lr (default "
                        "the preset's); 0 freezes them at --kernels (e.g. an oracle: how much "
                        "of the model mismatch the U-Net absorbs, docs/training.md)")
    for name in MOVED_TRAIN_FLAGS:     # hidden: given, run_train says where they went
        p.add_argument(name, help=argparse.SUPPRESS)
    add_flag(p, "--seed", "train", help="seed of the initial weights and the batch order "
                                        "(default 0)")
    add_flag(p, "--device", "train")
    add_flag(p, "--threads", "train",
             help="CPU threads of the training step (torch's intra-op threads; default: "
                  "torch's)")
    add_flag(p, "--amp", "train")
    p.add_argument("--no-amp", action="store_true", help="same as --amp off")
    p.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None,
                   help="U-Net convolutions in channels_last format (default: on CUDA only)")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the network (reports its warm-up time)")
    add_flag(p, "--loader-workers", "train")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/checkpoint.pt")
    p.add_argument("--overwrite", action="store_true", help="start RUN_DIR over")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_config_option(p, "lr = 1e-4", "the checkpoint's metadata (run_file)")
    mark_advanced(p, TRAIN_ADVANCED)
    p.set_defaults(func=run_train)

    # ---------------------------------------------------------------- eval
    p = sub.add_parser("eval", help="PSNR/SSIM/LPIPS, parameters, runtime, memory → tables",
                       description="Evaluate checkpoints on held-out pairs and write Table 1 "
                                   "(models) and Table 2 (EK-DUN schedules) as Markdown and "
                                   "JSON.")
    add_help_all(p)
    p.add_argument("checkpoints", nargs="+", help="checkpoint.pt files (or run folders)")
    p.add_argument("--data", required=True,
                   help="pairs folder, or a virtual-bench dataset (uses its test/)")
    p.add_argument("--out", required=True, help="folder for the tables")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.add_argument("--lpips-weights", help="local AlexNet weights for LPIPS "
                                           "(else $EKDUN_LPIPS_WEIGHTS; else unavailable)")
    p.add_argument("--include-training", action="store_true",
                   help="on the folder a run was trained on, score every pair, training pairs "
                        "included (default: only the pairs it held out)")
    add_flag(p, "--channel-order", "eval",
             note="the folder's (pairs.json; BGR for the DLMD layout), else the order each "
                  "checkpoint's training pairs were read in, else RGB")
    add_flag(p, "--device", "eval")
    add_flag(p, "--threads", "eval",
             help="CPU threads of the networks and metrics (torch's intra-op threads; "
                  "default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    mark_advanced(p, EVAL_ADVANCED)
    p.set_defaults(func=run_eval)

    # ---------------------------------------------------------------- reconstruct
    from ekdun.cli import classical_cmd, reconstruct_cmd

    reconstruct_cmd.register(sub)
    classical_cmd.register(sub)      # admm, reconstruct-classical: deprecated, hidden

    # ---------------------------------------------------------------- export-kernels
    # no help=: hidden (deprecated): `ekdun train` writes RUN/kernels_learned.npz every epoch;
    # kept for checkpoints of older runs
    p = sub.add_parser("export-kernels",
                       description="Deprecated: `ekdun train` writes the learned kernels as "
                                   "RUN/kernels_learned.npz. Writes a trained EK-DUN's "
                                   "kernels as a psfkit kernel file.")
    p.add_argument("checkpoint")
    p.add_argument("--out", required=True, help="kernel file (.npz)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=run_export_kernels, **{NOTICES: [EXPORT_KERNELS_NOTE]})

    # ---------------------------------------------------------------- moved to research
    register_moved(sub, "ekdun", MOVED)


def run_make_dataset(args: argparse.Namespace) -> int:
    from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench

    bounded_size(args.sensor, "--sensor", max_side=4096)
    bounded_size(args.grid, "--grid", max_side=MAX_GRID_SIDE, unit="positions")
    spec = VirtualBenchSpec(sensor_shape=tuple(args.sensor), n_train=args.n_train,
                            n_test=args.n_test, grid_shape=tuple(args.grid),
                            half_fov_deg=args.half_fov, aperture_mm=args.aperture,
                            photons=args.photons, grid_frames=args.grid_frames,
                            seed=args.seed)
    from ekdun.device import resolve_device

    # a worker process costs ~2 s to start (it imports torch): none for small datasets
    workers = args.threads or min(16, os.cpu_count() or 1,
                                  max(1, max(args.n_train, args.n_test) // 64))
    root = make_virtual_bench(args.out, spec, progress=not args.quiet,
                              device=resolve_device(args.device), workers=workers)
    _say(args, f"dataset: {root}")
    return 0


def run_train(args: argparse.Namespace) -> int:
    from ekdun.data.pairs import PairsDataset, match_downsample
    from ekdun.data.virtual_bench import resolve_split
    from ekdun.nets.builder import seed_kernel_model
    from ekdun.training import TrainOptions, train
    from psfkit.io.pairs import read_pairs
    from psfkit.io.read_options import choose

    for name, module in MOVED_TRAIN_FLAGS.items():
        if getattr(args, name[2:].replace("-", "_")) is not None:
            raise InvalidInputError(f"{name} left `ekdun train`: it is a research option, "
                                    f"now in {module} of a source checkout (CHANGELOG.md)")
    # flags are checked before any data is read (kernel-lr-scale 0 is given, not unset)
    for option, value in (("--schedule", args.schedule), ("--kernel-lr-scale",
                          args.kernel_lr_scale)):
        if value not in (None, "") and args.network != "ekdun":
            raise InvalidInputError(f"{option} applies to --network ekdun only")
    overrides: dict[str, Any] = {key: value for key, value in (
        ("schedule", args.schedule), ("iterations", args.iterations)) if value}
    root = resolve_split(args.data, "train")
    source = args.kernels or args.psf
    notices: list[str] = []
    if args.psf:
        # the one PSF loader (as ekdun admm PSF), binned like the pairs, in their channel order
        from psfkit.calibration.psf_image import load_psf_image

        probe = read_pairs(root, args.channel_order, check_pixels=False)
        seed = seed_kernel_model(load_psf_image(args.psf, probe.channel_order, "corner",
                                                args.downsample or 1, probe.white_level))
    else:
        seed = seed_kernel_model(source)
        # pairs are read the way the kernels' data was, unless the folder or a flag says so
        recorded = seed.data_read_options()
        notices += [n for n in [choose(args.channel_order, recorded.channel_order, "RGB",
                                       "--channel-order", str(source))[1]] if n]
        probe = read_pairs(root, args.channel_order, check_pixels=False, recorded=recorded)
    factor = match_downsample(probe.shape, seed, args.downsample,
                              where=f"the pairs in {root}", model_name=str(source))
    # the folder listed once: the probe was read with the dataset's channel order and options
    dataset = PairsDataset(probe, holdout=args.holdout or (), downsample=factor)
    if factor > 1 or dataset.holdout:
        _say(args, f"training on {len(dataset)} pairs of {root}"
                   + (f" (held out: {', '.join(dataset.holdout)})" if dataset.holdout else "")
                   + (f", binned {factor}x{factor} to {dataset.image_shape[1]}x"
                      f"{dataset.image_shape[2]}" if factor > 1 else ""))
    options = TrainOptions(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                           kernel_lr_scale=args.kernel_lr_scale, seed=args.seed,
                           amp="off" if args.no_amp else args.amp,
                           device=args.device, progress=not args.quiet, threads=args.threads,
                           channels_last=args.channels_last, compile=args.compile,
                           workers=args.loader_workers, run_file=run_file_record(args))
    result = train(args.run_dir, args.network, seed, dataset, args.preset,
                   overrides, options, resume=args.resume, overwrite=args.overwrite)
    last = result["history"][-1] if result["history"] else {}
    _say(args, f"trained {args.network}: {len(result['history'])} epochs, final loss "
               f"{last.get('train_loss', float('nan')):.4g}; {args.run_dir}")
    if "compile_warmup_s" in result:
        _say(args, f"torch.compile warm-up (first step): {result['compile_warmup_s']:.1f} s")
    for text in notices:   # after the work, so that an error stays the one line
        print(text, file=sys.stderr)
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from ekdun.evaluation import LPIPSMetric, evaluate_checkpoints, write_tables
    from psfkit.io import OutputTransaction

    set_threads(args)
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        folder = outputs.folder(args.out)   # checked before the evaluation
        lpips = LPIPSMetric(args.lpips_weights)
        results = evaluate_checkpoints(args.checkpoints, args.data, lpips, args.device,
                                       log=lambda line: _say(args, line),
                                       include_training=args.include_training,
                                       channel_order=args.channel_order)
        if not lpips.available:  # said after the work, so that an input error stays one line
            _say(args, lpips.reason)
        write_tables(folder, results, [lpips.reason] if lpips.reason else [])
    return 0


def run_export_kernels(args: argparse.Namespace) -> int:
    from ekdun.evaluation.evaluate import checkpoint_path
    from ekdun.training import export_kernels
    from psfkit.forward.kernelfile import save_kernels

    out = Path(args.out)
    if out.suffix != ".npz":
        raise InvalidInputError(f"{out}: kernel files are .npz")
    from psfkit.io import OutputTransaction

    with OutputTransaction(overwrite=args.overwrite) as outputs:
        staged = outputs.file(out)
        save_kernels(staged, export_kernels(checkpoint_path(args.checkpoint)))
    print(f"learned kernels: {out}", file=sys.stderr)
    return 0
