"""``ekdun admm`` (alias ``ekdun reconstruct-classical``): deprecated, hidden spellings of
``ekdun reconstruct`` with a PSF image (``admm PSF MEASUREMENT --out X.npy``) or a kernel file
(``admm --kernels MODEL.npz MEASUREMENT... --out X.npy|FOLDER``); they run unchanged for one
release, then print one note (docs/migration.md). The model builders and solver flags are
shared with ``ekdun reconstruct``, so both spellings give the same numbers.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ekdun.cli.vocabulary import add_flag, set_threads
from ekdun.errors import InvalidInputError
from ekdun.flag_ranges import flag
from psfkit.cli.vocabulary import NOTICES, deprecation_notices
from psfkit.io.validation import require_finite

# One TV default for both forms (the same solver and units): 3e-4, the best of four weights for
# the PSF form on a DLMD pair (research/notes/reconstruction-studies.md).
_DEFAULTS = {"psf": {"iterations": 100, "tv": 3e-4, "background": "corner"},
             "kernels": {"iterations": 100, "tv": 3e-4, "background": "none"}}
# ClassicalOptions' defaults and solvers, spelled out so that ``ekdun --help`` needs no torch
# (tests/e2e/test_cli_classical.py checks that they agree).
SOLVERS = ("auto", "admm")
# removed solvers: accepted for one release, run ADMM after one note line (docs/migration.md)
RETIRED_SOLVERS = {"pdhg": "note: --solver pdhg is deprecated: PDHG was removed; the ADMM-TV "
                           "solver runs instead (docs/migration.md)"}
#: The parser defaults of the solver flags that are not ``None`` (``ekdun reconstruct`` refuses
#: them with a checkpoint only when they differ from these).
SOLVER_DEFAULTS = {"solver": "auto", "nonneg": True, "tol": 0.0, "dtype": "float32"}
#: The old spellings, hidden; ``reconstruct-classical`` is an alias of ``admm``.
DEPRECATED_COMMANDS = ("admm", "reconstruct-classical")


def deprecated_note(command: str) -> str:
    """The one line ``ekdun admm`` / ``reconstruct-classical`` prints after its work."""
    return (f"note: `ekdun {command}` is deprecated: use `ekdun reconstruct MODEL "
            "MEASUREMENT... --out DIR` (MODEL: the kernel file, or the PSF image); this "
            "spelling will be removed in the next release (docs/migration.md)")


def add_solver_flags(p: argparse.ArgumentParser, command: str, form_note: str) -> None:
    """The options of the classical solver (``admm``, ``reconstruct``); ``form_note`` says
    which inputs they apply to in ``command``."""
    p.add_argument("--iterations", type=flag("--iterations"),
                   help=f"solver iterations{form_note} (default 100)")
    add_flag(p, "--tv", command)
    p.add_argument("--solver", choices=(*SOLVERS, *RETIRED_SOLVERS), default="auto",
                   metavar="{" + ",".join(SOLVERS) + "}",
                   help="admm, the closed-form ADMM-TV for every model (auto: the same)"
                        f"{form_note}")
    p.add_argument("--nonneg", action=argparse.BooleanOptionalAction, default=True,
                   help=f"constrain the image to >= 0{form_note} (default on)")
    p.add_argument("--tol", type=flag("--tol"), default=0.0,
                   help="stop when the relative change of the image falls below this"
                        f"{form_note} (default 0: run all iterations)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                   help=f"precision of the solver{form_note} (default float32)")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``admm`` and ``reconstruct-classical``, hidden (deprecated)."""
    # no help=: not listed by `ekdun --help`; the note is printed after the work (run_admm)
    p = sub.add_parser("admm", aliases=list(DEPRECATED_COMMANDS[1:]), description="""
        Deprecated: use `ekdun reconstruct MODEL MEASUREMENT... --out DIR` (MODEL: a kernel
        file or a PSF image). With a PSF image: its shift-invariant model (background
        subtracted, clipped to >= 0, unit sum per channel). With --kernels: the SI or
        eigen-kernel model exactly as fitted; folders of measurements in, a folder of
        reconstructions out.""")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="PSF MEASUREMENT, or with --kernels: measurement files and/or folders")
    p.add_argument("--kernels", help="kernel file (.npz) from psfkit fit-eigen / fit-pairs")
    p.add_argument("--out", required=True,
                   help="output .npy (a .png preview is written next to it); with --kernels "
                        "and a folder or several measurements: an output folder")
    add_solver_flags(p, "admm", "")
    p.add_argument("--downsample", type=flag("--downsample"),
                   help="box-downsample the inputs first (default: with --kernels, the factor "
                        "recorded in the kernel file; else 1)")
    p.add_argument("--background", choices=("none", "corner"),
                   help="subtract the mean of the [5:15, 5:15] corner (default: corner with a "
                        "PSF image, none with --kernels)")
    add_flag(p, "--channel-order", "admm",
             note="with --kernels, the order recorded in the kernel file, e.g. BGR for a "
                  "model fitted on the DLMD pairs; else RGB; outputs are always RGB")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output (file and preview, or folder)")
    add_flag(p, "--threads", "admm",
             help="CPU threads of the solver (torch's intra-op threads; default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_admm)


def fill_defaults(args: argparse.Namespace, form: str) -> None:
    """The defaults of the form (``"psf"`` or ``"kernels"``) for the flags left unset."""
    for name, value in _DEFAULTS[form].items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.solver in RETIRED_SOLVERS:   # its note joins the others, printed after the work
        setattr(args, NOTICES, [*deprecation_notices(args), RETIRED_SOLVERS[args.solver]])
        args.solver = "admm"


def run_admm(args: argparse.Namespace) -> int:
    # the note joins the deprecated flags' notes, printed by run_cli after the work
    # (``command``: the spelling used, set by ekdun's sub-parser action)
    setattr(args, NOTICES, [*deprecation_notices(args),
                            deprecated_note(getattr(args, "command", None) or "admm")])
    set_threads(args)
    fill_defaults(args, "kernels" if args.kernels else "psf")
    return run_with_kernels(args) if args.kernels else run_with_psf(args)


def classical_options(args: argparse.Namespace) -> Any:
    """The :class:`~ekdun.reconstruction.classical.ClassicalOptions` of the flags."""
    from ekdun.reconstruction.classical import ClassicalOptions

    return ClassicalOptions(solver=args.solver, tv=args.tv, iterations=args.iterations,
                            nonneg=args.nonneg, tol=args.tol, dtype=args.dtype)


def kernel_file_model(path: str, channel_order: str | None, downsample: int | None
                      ) -> tuple[Any, str, int, float | None, list[str]]:
    """A kernel file as fitted, and how to read its measurements (the flags overriding its
    record): ``(model, channel order, binning factor, white level, notices)``."""
    from psfkit.forward.kernelfile import load_kernels
    from psfkit.io.read_options import choose

    model = load_kernels(path)
    # inputs are read the way the model's data was, unless a flag says otherwise
    recorded = model.data_read_options()
    order, order_notice = choose(channel_order, recorded.channel_order, "RGB",
                                 "--channel-order", path)
    factor, factor_notice = choose(downsample, recorded.downsample, 1, "--downsample", path)
    notices = [n for n in (order_notice, factor_notice) if n]
    return model, order, factor, recorded.white_level, notices


def run_with_kernels(args: argparse.Namespace) -> int:
    from ekdun.reconstruction.classical import read_classical_measurement

    model, order, factor, white_level, notices = kernel_file_model(
        args.kernels, args.channel_order, args.downsample)
    out = Path(args.out)
    single = len(args.inputs) == 1 and Path(args.inputs[0]).is_file()
    if single and out.suffix == ".npy":
        def measurement() -> tuple[Any, Any]:
            y = read_classical_measurement(args.inputs[0], order, factor, args.background,
                                           white_level)
            require_finite(y, args.inputs[0])
            return model, y

        _reconstruct_one(args, out, measurement)
        return say_all(notices)
    if out.suffix:
        raise InvalidInputError(f"{out}: several measurements need an output folder, not a file")
    return reconstruct_into_folder(args, model, args.inputs, out, order, factor, white_level,
                                   notices)


def reconstruct_into_folder(args: argparse.Namespace, model: Any, inputs: list[str],
                            out: str | Path, order: str, factor: int,
                            white_level: float | None, notices: list[str]) -> int:
    """The classical solver on every measurement of ``inputs``, into the folder ``out``."""
    from ekdun.reconstruction.classical import reconstruct_folder

    written = reconstruct_folder(model, inputs, out, classical_options(args), order,
                                 args.overwrite, progress=not args.quiet, downsample=factor,
                                 background=args.background, white_level=white_level)
    return say_all(notices, f"{len(written)} reconstruction(s) in {out}")


def _reconstruct_one(args: argparse.Namespace, out: Path,
                     build: Callable[[], tuple[Any, Any]]) -> None:
    """Reconstruct ``build() -> (model, y)`` into ``out`` (.npy) and its preview, together."""
    from ekdun.reconstruction.classical import ModelReconstructor, write_reconstruction
    from psfkit.io import OutputTransaction

    options = classical_options(args)
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        staged, preview = outputs.file(out), outputs.file(out.with_suffix(".png"))
        model, y = build()
        recon = ModelReconstructor(model, options)
        recon.check(y, args.inputs[-1])
        result = recon(y, callback=None if args.quiet else _iteration_bar(args.iterations))
        write_reconstruction(staged, result.image, preview)
    print(f"{recon.solver} reconstruction {y.shape[1]}x{y.shape[2]} "
          f"({result.iterations} it, {result.seconds:.1f} s): {out}", file=sys.stderr)


def say_all(notices: list[str], done: str = "") -> int:
    """``done`` (what was written), then the notices, after the work so that an error stays
    the one line on stderr; the exit status 0."""
    for text in filter(None, [done, *notices]):
        print(text, file=sys.stderr)
    return 0


def _iteration_bar(total: int):  # a tqdm-driven callback
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc="reconstruct", unit="it")

    def step(iteration: int, change: float) -> None:
        bar.update(iteration - bar.n)
        if iteration % 10 == 0:
            bar.set_postfix_str(f"Δ {change:.1e}")
        if iteration >= total:
            bar.close()
    return step


def run_with_psf(args: argparse.Namespace) -> int:
    if len(args.inputs) != 2:
        raise InvalidInputError("give a PSF image and one measurement (or use --kernels "
                                "MODEL.npz with measurement files and folders)")
    out = Path(args.out)
    if out.suffix != ".npy":
        raise InvalidInputError(f"{out}: the output must be a .npy file")
    psf_path, measurement_path = args.inputs
    _reconstruct_one(args, out, lambda: psf_image_model(
        psf_path, measurement_path, args.channel_order or "RGB", args.downsample or 1,
        args.background))
    return 0


def psf_image_model(psf_path: str, measurement_path: str, channel_order: str, factor: int,
                    background: str) -> tuple[Any, Any]:
    """The shift-invariant kernel model of a PSF image for measurements like
    ``measurement_path``, and that measurement ``(C, H, W)``."""
    from ekdun.reconstruction.classical import psf_model, read_classical_measurement
    from psfkit.calibration.psf_image import psf_kernel
    from psfkit.io.images import read_image_float

    raw_psf = read_image_float(psf_path, channel_order)
    if min(raw_psf.shape[-2:]) // factor < 8:
        raise InvalidInputError(f"--downsample {factor}: {psf_path} "
                                f"({raw_psf.shape[-2]}x{raw_psf.shape[-1]}) would be smaller "
                                "than 8x8 pixels")
    # the one PSF treatment (background, binning, clipping, unit sum), as ekdun train --psf
    psf = psf_kernel(raw_psf, background, factor, psf_path)
    y = read_classical_measurement(measurement_path, channel_order, factor, background)
    require_finite(y, measurement_path)
    return psf_model(psf, y.shape[-2:], y.shape[0], where=psf_path), y
