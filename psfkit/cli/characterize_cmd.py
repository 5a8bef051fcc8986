"""``psfkit report``: characterize a measured PSF grid (and the hidden ``register``, ``mae``,
``warp`` it replaced, kept for one release)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psfkit.choices import FLOW_METHODS
from psfkit.cli.help_all import add_command, mark_advanced
from psfkit.cli.options import (
    add_grid_options,
    open_grid,
    preprocess_options,
    print_coverage,
)
from psfkit.cli.summaries import (
    astigmatism_line,
    gain_line,
    growth_line,
    print_verdict,
    shift_map_line,
)
from psfkit.cli.vocabulary import NOTICES, add_flag, command_name
from psfkit.io import OutputTransaction
from psfkit.io.flag_ranges import flag

# The characterization (scipy, OpenCV, matplotlib) is imported by the commands that run it,
# not when the parser is built (``psfkit --help`` stays fast).
if TYPE_CHECKING:
    from psfkit.characterization.characterize import GridCharacterization


def _common(p: argparse.ArgumentParser) -> None:
    add_grid_options(p)
    p.add_argument("--per-channel", action="store_true",
                   help="also register each colour channel separately (lateral colour): "
                        "printed as one shift grid per channel, and in the numbers "
                        "(results.json: positions[].channel_shifts)")
    add_flag(p, "--threads", command_name(p))


def _run(args: argparse.Namespace, steps: tuple[str, ...]) -> GridCharacterization:
    from psfkit.characterization.characterize import CharacterizeOptions, characterize_grid

    grid = open_grid(args)   # every image is checked as it is processed
    options = CharacterizeOptions(preprocess=preprocess_options(args), steps=steps,
                                  upsample=args.upsample,
                                  flow_method=getattr(args, "method", "dis"),
                                  per_channel=args.per_channel,
                                  mae_smoothing_px=getattr(args, "mae_smoothing", 1.0),
                                  min_quality=args.min_ncc, strict=args.strict)
    return characterize_grid(grid, options, progress=not args.quiet, workers=args.threads)


def _run_and_write_numbers(args: argparse.Namespace, steps: tuple[str, ...]
                           ) -> GridCharacterization:
    """:func:`_run`, then the numbers to ``--out`` (JSON/CSV, checked first) when given."""
    from psfkit.report.grid import check_numbers_path, write_numbers

    with OutputTransaction(overwrite=args.overwrite) as outputs:
        numbers = outputs.file(check_numbers_path(args.out)) if args.out else None
        result = _run(args, steps)
        if numbers is not None:
            write_numbers(result, numbers)
    return result


#: An irregular scan of more positions is summarised in the terminal (every position is in
#: the --out numbers, the report's positions.csv and results.json).
IRREGULAR_LINES = 12


def _scan_summary(values: np.ndarray, fmt: str, files: list[str]) -> None:
    """One line for a long irregular scan: the range and median, naming the extremes."""
    finite = np.isfinite(values)
    if not finite.any():
        print(f"  {len(values)} positions, none measured")
        return
    lo = int(np.nanargmin(values))
    hi = int(np.nanargmax(values))
    left = len(values) - int(finite.sum())
    print(f"  {int(finite.sum())} positions: min {format(values[lo], fmt).strip()} "
          f"({files[lo]}), median {format(float(np.nanmedian(values)), fmt).strip()}, max "
          f"{format(values[hi], fmt).strip()} ({files[hi]})"
          + (f", {left} not measured" if left else "")
          + "; every position in --out FILE.csv or the report's positions.csv")


def _grid_print(title: str, values: np.ndarray, fmt: str, result: GridCharacterization
                ) -> None:
    """``title``, then the values as the lattice, or one line per position of a scan."""
    print(title)
    width = len(format(0, fmt))
    if result.layout == "irregular":
        files = {(p.row, p.col): p.file for p in result.captured}
        if values.shape[1] > IRREGULAR_LINES:
            _scan_summary(values[0], fmt, [files.get((0, c), "?") for c in
                                           range(values.shape[1])])
            return
        for c, v in enumerate(values[0]):
            text = format(v, fmt) if np.isfinite(v) else "excluded".rjust(width)
            print(f"  #{c:<3d} {files[(0, c)]:24s} {text}")
        return

    marks = {"missing": "·", "excluded": "x"}

    def cell(v: float, state: str) -> str:
        if state in marks:
            return marks[state].rjust(width)
        return format(v, fmt) if np.isfinite(v) else " " * width

    for row, states in zip(values, result.status(), strict=True):
        print("  " + " ".join(cell(v, st) for v, st in zip(row, states, strict=True)))


#: ``psfkit register``, ``mae`` and ``warp`` are parts of ``psfkit report``: hidden
#: from ``psfkit --help``, they still run for one release and then print where ``report``
#: puts what they printed (docs/migration.md).
REPLACED_BY_REPORT = {
    "register": "the shifts are in DIR/positions.csv (shift_du_px, shift_dv_px) and "
                "DIR/results.json (positions[].shift_px, shift_map)",
    "mae": "the MAE is in DIR/positions.csv (mae, mae_gain_compensated; fractions, not %) "
           "and DIR/results.json (positions[].mae, gain_fit)",
    "warp": "the warp is in DIR/positions.csv (warp_residual_rms_px, warp_anisotropy, "
            "affine_*) and DIR/results.json (positions[].warp, warp_growth, warp_anisotropy)",
}


def replaced_note(command: str) -> str:
    """The one line a replaced command prints after its work (:data:`REPLACED_BY_REPORT`)."""
    return (f"note: `psfkit {command}` is replaced by `psfkit report GRID --out DIR`: "
            f"{REPLACED_BY_REPORT[command]}; this spelling will be removed in the next release "
            "(docs/migration.md)")


def _replaced(sub: argparse._SubParsersAction, name: str, description: str,
              run: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    # no help=: not listed by `psfkit --help`; the note is printed once the work is done
    # (psfkit.cli.main.run_cli), so that an error stays the one line on stderr
    p = sub.add_parser(name, description=f"{description} Replaced by `psfkit report`: "
                                         f"{REPLACED_BY_REPORT[name]}.")
    _common(p)
    p.add_argument("--out", help="write the numbers to FILE.json or FILE.csv")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=run, **{NOTICES: [replaced_note(name)]})
    return p


#: Flags of ``psfkit report`` that only ``--help-all`` lists: settings an optics engineer
#: rarely changes (the registration precision, the dense-flow method, the MAE's smoothing, the
#: dark-frame outlier threshold, the normalization, the registration-quality threshold).
REPORT_ADVANCED = ("--upsample", "--method", "--mae-smoothing", "--hot-pixel-sigma",
                   "--normalization", "--min-ncc", "--threads")


def register(sub: argparse._SubParsersAction) -> None:
    _replaced(sub, "register", """Register every PSF to the centre one (phase correlation,
        1/UPSAMPLE px) and fit the field-position -> shift map.""", run_register)
    m = _replaced(sub, "mae", """MAE of every PSF against the centre one after shift (and
        gain) compensation: the error of a shift-invariant model (paper Fig. 2).""", run_mae)
    m.add_argument("--mae-smoothing", type=flag("--mae-smoothing"), default=1.0, metavar="SIGMA",
                   help="Gaussian sigma (px) applied before the MAE to suppress sensor noise "
                        "(0 = raw pixels; default 1)")
    w = _replaced(sub, "warp", """Dense displacement field between the centre PSF and each
        registered PSF, split into an affine part (ECC) and a residual (dense flow) with its
        tangential/sagittal RMS.""", run_warp)
    w.add_argument("--method", choices=FLOW_METHODS, default="dis",
                   help="dense-flow method for the residual (default dis)")

    r = add_command(sub, "report", "characterize a PSF grid: shifts, gain, MAE, warp and a "
                                   "verdict, as an HTML report", """
        Register every PSF to the centre one, measure gain, MAE and warp, and write an HTML
        report with figures (PNG/PDF), results.json and positions.csv into DIR.""")
    _common(r)
    r.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (created atomically)")
    r.add_argument("--method", choices=FLOW_METHODS, default="dis",
                   help="dense-flow method for the warp residual (default dis)")
    r.add_argument("--mae-smoothing", type=flag("--mae-smoothing"), default=1.0, metavar="SIGMA",
                   help="Gaussian sigma (px) before the MAE (default 1)")
    r.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    mark_advanced(r, REPORT_ADVANCED)
    r.set_defaults(func=run_report)


def print_registration(result: GridCharacterization) -> None:
    fit = result.shift_fit
    print(f"registered {len(result.positions)} PSFs of {result.grid_root} ({result.layout}) "
          f"to the centre {result.center}")
    if fit is not None:
        print(shift_map_line(fit))
    shifts = result.table("shift")
    _grid_print("shift du (px):", shifts[..., 0], "8.2f", result)
    _grid_print("shift dv (px):", shifts[..., 1], "8.2f", result)
    print(f"registration quality (NCC): min {np.nanmin(result.table('quality')):.3f}")
    print_coverage(result)


def print_channel_shifts(result: GridCharacterization) -> None:
    """``--per-channel``: each colour channel's shift against the same channel of the centre
    PSF (lateral colour), one grid per channel and axis."""
    records = [p.channel_shifts for p in result.positions]
    if any(r is None for r in records):
        print("per-channel shifts: none (the grid has one channel)")
        return
    shifts = result._lattice(result.positions, [np.asarray(r, dtype=np.float64)
                                                for r in records])
    for c in range(shifts.shape[2]):
        for axis, name in ((0, "du"), (1, "dv")):
            _grid_print(f"channel {c} shift {name} (px):", shifts[:, :, c, axis], "8.2f",
                        result)


def _print_closing(args: argparse.Namespace, result: GridCharacterization) -> int:
    """The lines every characterization command ends with: per-channel shifts, warnings."""
    from psfkit.report.grid import warnings_for

    if args.per_channel:
        print_channel_shifts(result)
    for message in warnings_for(result):
        print(f"warning: {message}")
    return 0


def run_register(args: argparse.Namespace) -> int:
    result = _run_and_write_numbers(args, ("register",))
    print_registration(result)
    return _print_closing(args, result)


def run_mae(args: argparse.Namespace) -> int:
    result = _run_and_write_numbers(args, ("register", "gain", "mae"))
    if result.gain_fit is not None:
        print(gain_line(result.gain_fit))
    _grid_print(f"MAE vs the centre PSF, % of its light (sum |PSF - centre| / sum centre over "
                f"the PSFs' support; smoothing {args.mae_smoothing:g} px):",
                result.table("mae") * 100, "7.2f", result)
    _grid_print("after gain compensation, %:", result.table("mae_gain_compensated") * 100,
                "7.2f", result)
    print_coverage(result)
    return _print_closing(args, result)


def run_warp(args: argparse.Namespace) -> int:
    from psfkit.characterization.characterize import RELIABLE_OVERLAP

    result = _run_and_write_numbers(args, ("register", "gain", "warp"))
    _grid_print("residual displacement rms (px) after the affine part:",
                result.warp_table("residual_rms"), "6.3f", result)
    _grid_print("tangential / sagittal anisotropy:", result.warp_table("anisotropy"), "6.2f",
                result)
    print_coverage(result)
    print(f"{growth_line(result.warp_growth)} (positions with >= {RELIABLE_OVERLAP:.0%} of "
          "the centre PSF's light in their overlap)")
    print(astigmatism_line(result))
    return _print_closing(args, result)


def run_report(args: argparse.Namespace) -> int:
    from psfkit.report.grid import write_report

    out = Path(args.out)
    with OutputTransaction(overwrite=args.overwrite) as outputs:
        folder = outputs.folder(out)   # checked before the work
        result = _run(args, ("register", "gain", "mae", "warp", "verdict"))
        write_report(result, folder, overwrite=True)   # into the empty temporary folder
    if result.verdict is not None:
        print_verdict(result.verdict)
    print_registration(result)
    if result.gain_fit is not None:
        print(gain_line(result.gain_fit))
    print(growth_line(result.warp_growth))
    print(astigmatism_line(result))
    _print_closing(args, result)
    print(f"report: {out / 'report.html'}")
    return 0
