"""``psfkit simulate-grid`` and ``psfkit demo``: the virtual bench from the command line."""

from __future__ import annotations

import argparse
import dataclasses
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from psfkit.cli.help_all import add_command, mark_advanced
from psfkit.cli.run_file import add_config_option, run_file_record
from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.io import OutputTransaction, PsfGrid, read_grid
from psfkit.io.atomic import check_output
from psfkit.io.flag_ranges import flag
from psfkit.io.json_documents import read_json_file

# The virtual bench (scipy) is imported by the commands that run it, not when the parser is
# built (``psfkit --help`` stays fast).
if TYPE_CHECKING:
    from psfkit.simulate import BenchConfig


#: The demo's sensor binning: the coarsest at which every field effect of the bench is still
#: significant (at 6x the astigmatism is not), about 25 MB written; 2x writes a 189 MB grid
#: (research/notes/characterization-studies.md).
DEMO_DOWNSAMPLE = 4


def add_bench_options(p: argparse.ArgumentParser, downsample: int = 1) -> None:
    """Options that build a :class:`~psfkit.simulate.BenchConfig` (shared by bench commands)."""
    g = p.add_argument_group("virtual camera")
    g.add_argument("--bench-config", metavar="JSON",
                   help="JSON file of BenchConfig parameters (options below override it)")
    g.add_argument("--downsample", type=flag("--downsample"), default=None,
                   help=f"sensor binning factor for fast runs (default {downsample})")
    g.add_argument("--seed", type=flag("--seed"), default=None,
                   help="diffuser and noise seed (default 0)")
    g.add_argument("--diffusion-angle", type=flag("--diffusion-angle"), default=None,
                   metavar="DEG",
                   help="diffuser FWHM scattering angle (default 1.0)")
    g.add_argument("--gap-mm", type=flag("--gap-mm"), default=None,
                   help="diffuser-sensor distance (default 14.6)")
    g.add_argument("--peak-fraction", type=flag("--peak-fraction"), default=None,
                   help="exposure: brightest on-axis pixel as a fraction of full well "
                        "(default 0.8; >1 saturates)")
    g.add_argument("--mono", action="store_true", help="monochrome camera (530 nm)")
    g.add_argument("--plane-wave", action="store_true",
                   help="plane-wave sources instead of spherical waves from the monitor")
    p.set_defaults(default_downsample=downsample)


def bench_config_from_args(args: argparse.Namespace) -> BenchConfig:
    from psfkit.simulate import BenchConfig

    values: dict = {}
    if args.bench_config:
        path = Path(args.bench_config)
        values = read_json_file(path)
        if not isinstance(values, dict):
            raise InvalidInputError(f"{path}: expected a JSON object of BenchConfig parameters")
    config = BenchConfig.from_dict(values)
    overrides = {
        "downsample": args.downsample if args.downsample is not None
        else (None if "downsample" in values else args.default_downsample),
        "seed": args.seed, "diffusion_angle_deg": args.diffusion_angle, "gap_mm": args.gap_mm,
        "peak_fraction": args.peak_fraction,
        "wavelengths_nm": (530.0,) if args.mono else None,
        "spherical_source": False if args.plane_wave else None,
    }
    try:
        return dataclasses.replace(config, **{k: v for k, v in overrides.items() if v is not None})
    except TypeError as exc:
        raise ConfigurationError(str(exc)) from None


#: Flags that only ``--help-all`` lists: the capture and the optics of the virtual
#: camera beyond its size, binning and seed (their defaults are the embedded bench's).
SIMULATE_ADVANCED = ("--extent", "--format", "--no-dark", "--frames", "--backend")
BENCH_ADVANCED = ("--bench-config", "--diffusion-angle", "--gap-mm", "--peak-fraction",
                  "--mono", "--plane-wave")


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "simulate-grid", "simulate a measured PSF grid with the virtual bench", """
        Simulate a diffuser camera (thin random phase diffuser, angular-spectrum propagation,
        sensor noise) and write an N x M grid of point-source images in the PSF-grid format,
        with ground truth in DIR/ground_truth/.""")
    p.add_argument("--out", required=True, help="output grid folder (created atomically)")
    p.add_argument("--rows", type=flag("--rows"), default=9, help="grid rows (default 9)")
    p.add_argument("--cols", type=flag("--cols"), default=9, help="grid columns (default 9)")
    p.add_argument("--extent", type=flag("--extent"), default=1.0,
                   help="fraction of the field of view the grid spans (default 1.0)")
    p.add_argument("--format", choices=("tiff", "png", "npy"), default="tiff",
                   help="image file type (default tiff, 16-bit)")
    p.add_argument("--no-dark", action="store_true", help="do not capture a dark frame")
    p.add_argument("--frames", type=flag("--frames"), default=1, metavar="N",
                   help="frames averaged per position and for the dark frame: the noise falls "
                        "as 1/sqrt(N); N > 1 writes the float32 mean (TIFF or npy) (default "
                        "1: one raw 16-bit frame)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--backend", choices=("auto", "torch", "numpy"), default="auto",
                   help="optics backend: torch (float32, CUDA if present; same clean PSFs to "
                        "~5e-7 but another noise realization), numpy (the float64 reference "
                        "path, file for file as before); auto (default) = torch if installed")
    add_bench_options(p)
    add_config_option(p, "frames = 4", "the grid's manifest.json")
    mark_advanced(p, SIMULATE_ADVANCED + BENCH_ADVANCED)
    p.set_defaults(func=run_simulate)

    d = add_command(sub, "demo", "simulate a grid with the virtual bench and characterize it", f"""
        The main job on the embedded default: simulate a 9 x 9 grid of a diffuser camera whose
        PSF varies over the field (binned {DEMO_DOWNSAMPLE}x by default), characterize it
        (registration, gain, MAE, warp), write the HTML report, compare the measurements with
        the ground truth and fit the eigen-kernels.""")
    d.add_argument("--out", default="psfkit-demo", help="output folder (default psfkit-demo)")
    d.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    add_bench_options(d, downsample=DEMO_DOWNSAMPLE)
    add_config_option(d, "gap-mm = 10", "the grid's manifest.json")
    mark_advanced(d, ("--downsample", *BENCH_ADVANCED))
    d.set_defaults(func=run_demo)


def run_simulate(args: argparse.Namespace) -> int:
    from psfkit.simulate import simulate_grid

    config = bench_config_from_args(args)
    out = simulate_grid(args.out, config, grid_shape=(args.rows, args.cols), extent=args.extent,
                        dark_frame=not args.no_dark, suffix=f".{args.format}",
                        overwrite=args.overwrite, progress=not args.quiet, backend=args.backend,
                        frames=args.frames, run_file=run_file_record(args))
    print(f"wrote {args.rows} x {args.cols} grid to {out}")
    return 0


def run_demo(args: argparse.Namespace) -> int:
    from psfkit.simulate import simulate_grid

    config = bench_config_from_args(args)
    out = check_output(args.out, "folder", args.overwrite)
    grid_dir, report_dir = out / "grid", out / "report"
    new_grid = not grid_dir.exists()
    try:
        # the report and kernels appear together; the grid (which they name) is written
        # first, under its final name, and removed again if the demo fails
        with OutputTransaction(overwrite=True) as outputs:
            staged = (outputs.folder(report_dir), outputs.file(out / "kernels.npz"),
                      outputs.folder(out / "kernels-figures"))
            # the ground truth without the clean PSFs (read_ground_truth computes them again
            # when asked): 378 MB of float32 at 2x binning that a user rarely reads
            simulate_grid(grid_dir, config, overwrite=True, progress=not args.quiet,
                          clean_psfs=False, run_file=run_file_record(args))
            _demo_steps(args, config, grid_dir, *staged)
    except BaseException:
        if new_grid:
            shutil.rmtree(grid_dir, ignore_errors=True)
        raise
    print(f"report: {report_dir / 'report.html'}")
    print(f"kernels for ekdun: {out / 'kernels.npz'} (figures in {out / 'kernels-figures'})")
    return 0


def _demo_steps(args: argparse.Namespace, config: BenchConfig, grid_dir: Path,
                report_tmp: Path, kernels_tmp: Path, figures_tmp: Path) -> None:
    """Characterize the simulated grid and fit its eigen-kernels, into the staged outputs."""
    from psfkit.characterization.characterize import (
        RELIABLE_OVERLAP,
        CharacterizeOptions,
        characterize_grid,
    )
    from psfkit.cli.summaries import astigmatism_line, growth_line
    from psfkit.report.grid import write_report
    from psfkit.simulate import read_ground_truth

    grid = read_grid(grid_dir)
    truth = read_ground_truth(grid_dir)
    c, h, w = grid.image_shape
    print(f"virtual bench: {grid.grid_shape[0]} x {grid.grid_shape[1]} PSFs of {h} x {w} x {c} "
          f"({grid.dtype}), field up to {np.abs(truth.field_deg).max():.2f} deg, in {grid_dir}")
    result = characterize_grid(grid, CharacterizeOptions(), progress=not args.quiet)
    write_report(result, report_tmp, overwrite=True)

    error = np.hypot(*np.moveaxis(result.table("shift") - truth.shift_px, -1, 0))
    reliable = result.table("support_overlap") >= RELIABLE_OVERLAP
    print(f"shift error vs ground truth: {np.sqrt(np.mean(error[reliable] ** 2)):.3f} px rms "
          f"where >= {RELIABLE_OVERLAP:.0%} of the centre PSF's light is in the overlap "
          f"({reliable.sum()} positions), {np.sqrt(np.mean(error ** 2)):.3f} px rms overall")
    fit = result.shift_fit
    if fit is not None:
        print(f"magnification: measured {fit.estimates['magnification'].text('.5f')}, true "
              f"{truth.info['magnification_px_per_monitor_px']:.5f} px per monitor px")
    gain_error = np.abs(result.table("gain") / truth.gain - 1)
    print(f"gain error: {100 * gain_error[reliable].max():.2f}% max; cos^n fit n = "
          f"{result.gain_fit.estimate.text('.2f')} (true {config.vignetting_exponent:g})")
    print(f"{growth_line(result.warp_growth)} (oblique-incidence astigmatism: p = 2)")
    print(astigmatism_line(result))
    if result.verdict is not None:
        print(f"verdict: {result.verdict.sentence()}")
    _demo_eigen_fit(grid, kernels_tmp, figures_tmp, quiet=args.quiet)


def _demo_eigen_fit(grid: PsfGrid, kernels: Path, figures: Path, quiet: bool) -> None:
    """The demo's last step: the eigen-kernel fit that seeds EK-DUN (as ``psfkit fit-eigen``)."""
    from psfkit.cli.fit_cmd import write_fit_figures
    from psfkit.cli.summaries import pm
    from psfkit.fitting.grid.fit import fit_eigen_grid
    from psfkit.fitting.grid.options import EigenFitOptions
    from psfkit.forward.kernelfile import save_kernels

    result = fit_eigen_grid(grid, EigenFitOptions(), progress=not quiet)
    save_kernels(kernels, result.kernel_model())
    write_fit_figures(result, figures, overwrite=True)
    if result.cv is not None:
        sigmas = result.cv["held_out_sigma"]
        errors = ", ".join(f"{name} {pm(err, sigmas[name], '.3f')}" for name, err
                           in result.cv["held_out_relative_error"].items())
        print(f"eigen-kernels: held-out relative error {errors}")
