"""``ekdun reconstruct MODEL MEASUREMENT... --out DIR``: one command for a checkpoint, a kernel
file or a PSF image (:func:`model_kind`); a flag of the other kind of model is refused."""

from __future__ import annotations

import argparse
from pathlib import Path

from ekdun.cli.vocabulary import add_flag, set_threads
from ekdun.errors import InvalidInputError
from ekdun.flag_ranges import flag
from psfkit.cli.help_all import add_command, mark_advanced

#: Suffixes of the PSF images ``reconstruct`` accepts as MODEL
#: (:data:`psfkit.io.images.IMAGE_SUFFIXES`, spelled out so that ``--help`` needs no NumPy).
PSF_SUFFIXES = (".tif", ".tiff", ".png", ".npy")
#: Flags that only ``--help-all`` lists: solver details, the network's autocast, threads.
ADVANCED = ("--background", "--solver", "--nonneg", "--tol", "--dtype", "--amp", "--threads")
#: Flags of the classical forms only (a kernel file or a PSF image).
CLASSICAL_ONLY = ("--iterations", "--tv", "--background", "--solver", "--nonneg", "--tol",
                  "--dtype")


def model_kind(path: str | Path) -> str:
    """``"checkpoint"``, ``"kernels"`` or ``"psf"``: what the MODEL file is, by its name
    (:class:`InvalidInputError` for none of them)."""
    p = Path(path)
    if p.is_dir():
        if (p / "checkpoint.pt").is_file():
            return "checkpoint"
        raise InvalidInputError(f"{p}: a folder without checkpoint.pt is not a model (give a "
                                "checkpoint .pt or run folder, a kernel file .npz or a PSF "
                                "image)")
    if not p.is_file():
        raise InvalidInputError(f"{p}: no such model file")
    suffix = p.suffix.lower()
    if suffix == ".pt":
        return "checkpoint"
    if suffix == ".npz":
        return "kernels"
    if suffix in PSF_SUFFIXES:
        return "psf"
    raise InvalidInputError(f"{p}: not a model: give a checkpoint (.pt, or a run folder), a "
                            "kernel file (.npz) or a PSF image (.npy, .png, .tif)")


def register(sub: argparse._SubParsersAction) -> None:
    from ekdun.cli.classical_cmd import add_solver_flags

    p = add_command(sub, "reconstruct",
                    "reconstruct measurements with a checkpoint, a kernel file or a PSF", """
        MODEL is a trained checkpoint (the network), a kernel file (classical ADMM-TV with the
        model as fitted) or a PSF image (classical ADMM-TV with its shift-invariant model:
        background subtracted, clipped to >= 0, unit sum per channel). Writes NAME.npy (H x W
        x C float32, RGB) and a NAME.png preview per measurement into the --out folder,
        atomically.""")
    p.add_argument("model", metavar="MODEL",
                   help="checkpoint (.pt or run folder), kernel file (.npz) or PSF image")
    p.add_argument("measurements", nargs="+", metavar="MEASUREMENT",
                   help="image files (npy, png, tiff) or folders of them")
    p.add_argument("--out", required=True, help="output folder (NAME.npy + NAME.png)")
    add_solver_flags(p, "reconstruct", " (kernel file or PSF image)")
    add_flag(p, "--channel-order", "reconstruct",
             note="the order the model's data was read in (checkpoint, kernel file), e.g. BGR "
                  "for DLMD; else RGB; outputs are always RGB")
    p.add_argument("--downsample", type=flag("--downsample"), metavar="N",
                   help="bin the measurements (and a PSF image) N x N (default: as the model's "
                        "data was, from the checkpoint or kernel file; else 1)")
    p.add_argument("--background", choices=("none", "corner"),
                   help="subtract the mean of the [5:15, 5:15] corner of each image (default: "
                        "corner with a PSF image, none with a kernel file)")
    add_flag(p, "--device", "reconstruct",
             note="auto; a checkpoint's network runs there, classical reconstruction on the "
                  "CPU")
    add_flag(p, "--amp", "reconstruct", note="auto; checkpoints only")
    add_flag(p, "--threads", "reconstruct",
             help="CPU threads (torch's intra-op threads; default: torch's)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    mark_advanced(p, ADVANCED)
    p.set_defaults(func=run_reconstruct)


def _given(args: argparse.Namespace, option: str) -> bool:
    """Whether ``option`` was set to something else than its parser default."""
    from ekdun.cli.classical_cmd import SOLVER_DEFAULTS

    dest = option.lstrip("-").replace("-", "_")
    return getattr(args, dest) != SOLVER_DEFAULTS.get(dest)


def run_reconstruct(args: argparse.Namespace) -> int:
    kind = model_kind(args.model)
    if Path(args.out).suffix.lower() in (".npy", ".png"):
        raise InvalidInputError(f"{args.out}: --out is a folder (NAME.npy and NAME.png are "
                                "written in it)")
    set_threads(args)
    if kind == "checkpoint":
        for option in CLASSICAL_ONLY:
            if _given(args, option):
                raise InvalidInputError(f"{option} is for a kernel file or a PSF image, not "
                                        f"for the checkpoint {args.model}")
        return _run_network(args)
    if args.amp != "auto":
        raise InvalidInputError(f"--amp is for a checkpoint, not for the "
                                f"{'kernel file' if kind == 'kernels' else 'PSF image'} "
                                f"{args.model}")
    if args.device not in ("auto", "cpu"):
        raise InvalidInputError(f"--device {args.device}: classical reconstruction (with "
                                f"{args.model}) runs on the CPU")
    return _run_classical(args, kind)


def _run_network(args: argparse.Namespace) -> int:
    from ekdun.cli.classical_cmd import say_all
    from ekdun.evaluation.evaluate import checkpoint_path
    from ekdun.reconstruction import reconstruct_files

    notices: list[str] = []
    written = reconstruct_files(checkpoint_path(args.model), args.measurements, args.out,
                                args.channel_order, args.device, args.overwrite,
                                args.amp, downsample=args.downsample, notify=notices.append)
    return say_all(notices, f"{len(written)} reconstruction(s) in {args.out}")


def _run_classical(args: argparse.Namespace, kind: str) -> int:
    """A kernel file or PSF image: the model, then the classical solver on every measurement."""
    from ekdun.cli import classical_cmd as cc
    from ekdun.reconstruction.reconstruct import measurement_files

    cc.fill_defaults(args, kind)
    if kind == "kernels":
        model, order, factor, white_level, notices = cc.kernel_file_model(
            args.model, args.channel_order, args.downsample)
    else:
        # the PSF's model is built for the size of the first measurement; every other one is
        # checked against it before anything is computed
        order, factor, white_level, notices = args.channel_order or "RGB", \
            args.downsample or 1, None, []
        first = measurement_files(args.measurements)[0]
        model, _ = cc.psf_image_model(args.model, str(first), order, factor, args.background)
    return cc.reconstruct_into_folder(args, model, args.measurements, args.out, order, factor,
                                      white_level, notices)
