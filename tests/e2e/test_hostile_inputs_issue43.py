"""Issue 43, item 8: the last hostile inputs, through the real command lines.

The one-line refusals (empty paths, frames too small to hold a PSF, flags and input files
blamed instead of the outputs they spoiled) are rows of ``test_bad_inputs.py`` (class 15);
this file holds what a table row cannot check:

- ``--debug`` after the sub-command (the hint of every internal-error line) works in both CLIs;
- an interrupted or failing command's last line on stderr is its own line, not a progress bar
  redrawn after it (``ekdun make-dataset`` under SIGTERM, and any command with a bar);
- an empty value is refused for every path or name argument of both CLIs, before any work,
  and ``register --out ''`` prints no summary;
- a grid of frames at the minimum size (12 × 12 px) is accepted and registers to the truth;
- the limits behind the new refusals: kernel gain, photons, saturation level.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]


def _env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    for key in ("PSFKIT_DEBUG", "EKDUN_DEBUG"):
        env.pop(key, None)
    return env


def _cli(cli: str, *args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    module = "psfkit.cli" if cli == "psfkit" else "ekdun.cli"
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True,
                          text=True, env=_env(), cwd=cwd, timeout=300)


def _last_line(stderr: str) -> str:
    """The last non-blank line as a terminal shows it (a bar redraws its line with ``\\r``)."""
    return [line for line in stderr.replace("\r", "\n").splitlines() if line.strip()][-1]


# ------------------------------------------------------------------ --debug anywhere


@pytest.mark.parametrize("cli, args", [
    ("psfkit", ["info", "{missing}", "--debug"]),
    ("psfkit", ["report", "{missing}", "--out", "{tmp}/rep", "--debug", "--quiet"]),
    ("ekdun", ["export-kernels", "{missing}", "--out", "{tmp}/k.npz", "--debug"]),
])
def test_debug_after_the_subcommand_prints_the_traceback(tmp_path, cli, args):
    argv = [a.format(missing=tmp_path / "missing", tmp=tmp_path) for a in args]
    done = _cli(cli, *argv)
    assert "unrecognized arguments" not in done.stderr
    assert done.returncode != 0 and "Traceback" in done.stderr, done.stderr[-1000:]
    assert not (tmp_path / "rep").exists() and not (tmp_path / "k.npz").exists()


def test_debug_after_a_double_dash_is_an_argument_not_the_flag():
    from psfkit.cli.main import split_debug

    assert split_debug("psfkit", ["report", "g", "--debug"]) == (True, ["report", "g"])
    assert split_debug("psfkit", ["info", "--", "--debug"]) == (False,
                                                               ["info", "--", "--debug"])


# ------------------------------------------------------------------ the last line is ours

#: A command run through the real runner that opens a progress bar, advances it, and then
#: is sent SIGTERM (``term``) or fails (``fail``) while the bar is still open.
BAR_COMMAND = """
import argparse, importlib, os, signal, sys, time
from tqdm.auto import tqdm
main = importlib.import_module("psfkit.cli.main")

def command(args):
    bar = tqdm(total=10, desc="work", unit="step", leave=sys.argv[2] == "leave")
    for _ in range(3):
        bar.update(1)
    if sys.argv[1] == "term":
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
    raise main.PsfkitError("in.npy: refused")

parser = argparse.ArgumentParser(prog="psfkit")
parser.set_defaults(func=command)
sys.exit(main.run_cli("psfkit", parser, []))
"""


@pytest.mark.parametrize("leave", ["leave", "clear"])
@pytest.mark.parametrize("how, status, line", [
    ("term", 143, "psfkit: interrupted (SIGTERM); unfinished outputs removed"),
    ("fail", 2, "psfkit: error: in.npy: refused"),
])
def test_the_commands_own_line_is_the_last_one_with_a_bar_open(how, status, line, leave):
    done = subprocess.run([sys.executable, "-c", BAR_COMMAND, how, leave], capture_output=True,
                          text=True, env=_env(), cwd=REPO, timeout=120)
    assert done.returncode == status, done.stderr
    assert _last_line(done.stderr) == line, repr(done.stderr[-300:])
    assert done.stderr.count(line) == 1


#: A command that builds an object whose constructor is interrupted by SIGTERM (``term``)
#: or completes (``done``) before its destructor, which fails without the attribute the
#: constructor did not reach (as imageio's Pillow plugin does).
HALF_BUILT_COMMAND = """
import argparse, importlib, os, signal, sys, time
main = importlib.import_module("psfkit.cli.main")

class Writer:
    def __init__(self, interrupt):
        if interrupt:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(30)
        self.pending = []

    def __del__(self):
        del self.unset_attribute

def command(args):
    Writer(sys.argv[1] == "term")

parser = argparse.ArgumentParser(prog="psfkit")
parser.set_defaults(func=command)
sys.exit(main.run_cli("psfkit", parser, sys.argv[2:]))
"""


@pytest.mark.parametrize("how, debug, status, reported", [
    ("term", False, 143, False),   # a consequence of the interruption: not shown
    ("term", True, 143, True),     # --debug shows everything
    ("done", False, 0, True),      # a destructor failing on its own is still reported
])
def test_a_half_built_objects_destructor_does_not_follow_the_interruption_line(
        how, debug, status, reported):
    done = subprocess.run([sys.executable, "-c", HALF_BUILT_COMMAND, how]
                          + (["--debug"] if debug else []),
                          capture_output=True, text=True, env=_env(), cwd=REPO, timeout=120)
    assert done.returncode == status, done.stderr
    assert ("Exception ignored in" in done.stderr) == reported, done.stderr
    if how == "term":
        assert _last_line(done.stderr) == \
            "psfkit: interrupted (SIGTERM); unfinished outputs removed", done.stderr


def test_sigterm_during_make_dataset_ends_with_the_interruption_line(tmp_path):
    """The sweep's case: SIGTERM while ``ekdun make-dataset`` draws its scenes bar."""
    out = tmp_path / "ds"
    proc = subprocess.Popen([sys.executable, "-m", "ekdun.cli", "make-dataset", str(out),
                             "--sensor", "16", "16", "--grid", "3", "3", "--n-train", "20000",
                             "--threads", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(),
                            cwd=REPO)
    seen, err = threading.Event(), bytearray()

    def read() -> None:
        while chunk := proc.stderr.read1(4096):
            err.extend(chunk)
            if b"scenes (train)" in err:
                seen.set()

    reader = threading.Thread(target=read)
    reader.start()
    try:
        assert seen.wait(240), err.decode()[-1000:]
        time.sleep(0.5)                       # a few scenes into the bar
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(120) == 128 + signal.SIGTERM
    finally:
        proc.kill()
        reader.join(30)
    stderr = err.decode()
    assert _last_line(stderr) == "ekdun: interrupted (SIGTERM); unfinished outputs removed", \
        repr(stderr[-400:])
    assert "Traceback" not in stderr
    assert not out.exists()


# ------------------------------------------------------------------ empty paths and names


def _string_arguments() -> list[tuple[str, str, str, bool, str]]:
    """``(cli, command, argument, positional, shown)`` for every argument of both CLIs that
    takes free text (a path or a name): no ``type=`` conversion and no fixed choices;
    ``shown`` is how argparse names it in messages (``INPUT`` for a metavar)."""
    from ekdun.cli import build_parser as ekdun_parser
    from psfkit.cli.main import build_parser as psfkit_parser

    found = []
    for cli, parser in (("psfkit", psfkit_parser()), ("ekdun", ekdun_parser())):
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        seen: set[int] = set()
        for command, p in sub.choices.items():
            if id(p) in seen:
                continue
            seen.add(id(p))
            for action in p._actions:
                if action.type is None and not action.choices and action.nargs != 0 \
                        and not isinstance(action, argparse._HelpAction):
                    name = action.option_strings[0] if action.option_strings else action.dest
                    found.append((cli, command, name, not action.option_strings,
                                  argparse._get_action_name(action)))
    return found


def test_every_path_or_name_argument_refuses_an_empty_value(tmp_path, capsys, monkeypatch):
    from ekdun.cli import main as ekdun_main
    from psfkit.cli import main as psfkit_main

    monkeypatch.chdir(tmp_path)   # Path('') is the current folder: nothing may appear in it
    arguments = _string_arguments()
    assert len(arguments) > 50
    # 13: `ekdun oracle --out` and `psfkit compare --out` left with their commands (research/,
    # issue 44)
    assert sum(1 for _, _, name, _, _ in arguments if name == "--out") >= 13
    for cli, command, name, positional, shown in arguments:
        argv = [command, ""] if positional else [command, name, ""]
        if positional and name != _first_positional(arguments, cli, command):
            continue   # an empty later positional is reached after the first: same rule
        status = (psfkit_main if cli == "psfkit" else ekdun_main)(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert status == 2, (cli, command, name)
        assert len(err) == 1 and f"argument {shown}: must not be empty" in err[0], err
    assert list(tmp_path.iterdir()) == []


def _first_positional(arguments, cli: str, command: str) -> str:
    return next(n for c, cmd, n, pos, _ in arguments if c == cli and cmd == command and pos)


def test_register_with_an_empty_out_prints_only_the_error(grid_3x3, tmp_path):
    done = _cli("psfkit", "register", str(grid_3x3), "--out", "", "--quiet", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stdout == ""                     # no summary
    assert done.stderr.strip().splitlines() == [
        "psfkit: error: argument --out: must not be empty (see psfkit register --help)"]
    assert list(tmp_path.iterdir()) == []


def test_an_output_transaction_refuses_an_empty_path(tmp_path, monkeypatch):
    from psfkit.errors import InvalidInputError
    from psfkit.io import OutputTransaction

    monkeypatch.chdir(tmp_path)
    for declare in ("file", "folder"):
        with pytest.raises(InvalidInputError, match="empty path"), \
                OutputTransaction(overwrite=True) as outputs:
            getattr(outputs, declare)("")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ frame size


def _gaussian_grid(out: Path, side: int, step: float = 1.5) -> Path:
    """A 3 × 3 grid of compact Gaussian PSFs (σ ≈ 1.2 px) on ``side`` × ``side`` 12-bit
    frames, ``step`` px apart per 5° of field: the true shift of (r, c) is
    ``((c - 1) step, (r - 1) step)``."""
    import tifffile

    out.mkdir(parents=True)
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:side, 0:side].astype(float)
    positions = []
    for r in range(3):
        for c in range(3):
            cv, cu = (side - 1) / 2 + (r - 1) * step, (side - 1) / 2 + (c - 1) * step
            sigma = 1.2 * (1 + 0.1 * abs(r - 1) + 0.05 * abs(c - 1))
            psf = np.exp(-((v - cv) ** 2 + (u - cu) ** 2) / (2 * sigma**2))
            raw = np.clip(np.round(64 + 3000 * psf + rng.normal(0, 3, psf.shape)), 0, 4095)
            name = f"psf_r{r:02d}_c{c:02d}.tiff"
            tifffile.imwrite(out / name, raw.astype(np.uint16))
            positions.append({"file": name, "row": r, "col": c,
                              "field_deg": [5.0 * (c - 1), 5.0 * (r - 1)]})
    (out / "manifest.json").write_text(json.dumps({
        "format": "psfkit-grid", "version": 1, "grid_shape": [3, 3], "bit_depth": 12,
        "black_level": 64.0, "positions": positions}))
    return out


def test_frames_of_the_minimum_size_register_to_the_truth_one_less_is_refused(tmp_path):
    from psfkit.io.validation import MIN_PSF_SIDE

    small = _gaussian_grid(tmp_path / "below", MIN_PSF_SIDE - 1)
    done = _cli("psfkit", "info", str(small), "--quiet")
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert f"psf_r00_c00.tiff: image of {MIN_PSF_SIDE - 1}×{MIN_PSF_SIDE - 1} px is too small " \
           "to hold a PSF" in done.stderr

    grid = _gaussian_grid(tmp_path / "at", MIN_PSF_SIDE)
    done = _cli("psfkit", "register", str(grid), "--out", str(tmp_path / "r.json"), "--quiet")
    assert done.returncode == 0, done.stderr
    result = json.loads((tmp_path / "r.json").read_text())
    shifts = {(p["row"], p["col"]): p["shift_px"] for p in result["positions"]}
    assert len(shifts) == 9                                  # every position accepted
    for (r, c), (du, dv) in shifts.items():
        assert du == pytest.approx(1.5 * (c - 1), abs=0.01), (r, c)
        assert dv == pytest.approx(1.5 * (r - 1), abs=0.01), (r, c)


# ------------------------------------------------------------------ limits behind the refusals


def test_kernel_gain_limits_keep_the_forward_model_finite(tmp_path):
    """At the upper limit the forward model of a unit scene is finite in float32; beyond it
    the kernel file is refused when written and when read, by name; so is one below the lower
    limit."""
    from psfkit.errors import ModelFileError
    from psfkit.fitting.pairs.fit import predict
    from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
    from psfkit.io.validation import MAX_KERNEL_GAIN, MIN_KERNEL_GAIN

    kernels = np.zeros((1, 1, 8, 8), np.float32)
    kernels[0, 0, 2:6, 2:6] = MAX_KERNEL_GAIN / 16          # sums to the limit
    model = KernelModel(kernels=kernels, basis="si", channels=("L",), sensor_shape=(16, 16))
    y = predict(model, np.ones((1, 1, 16, 16), np.float32))
    assert np.all(np.isfinite(y)) and y.max() == pytest.approx(MAX_KERNEL_GAIN, rel=1e-3)
    with pytest.raises(ModelFileError, match=r"kernel 'base' \(L\) sums to 1\.1e\+12"):
        KernelModel(kernels=kernels * np.float32(1.1), basis="si", channels=("L",))
    path = save_kernels(tmp_path / "k.npz", model)
    with np.load(path) as data:
        np.savez(tmp_path / "big.npz", kernels=data["kernels"] * np.float32(1.1),
                 metadata=data["metadata"])
    with pytest.raises(ModelFileError, match=r"big\.npz: kernel 'base'"):
        load_kernels(tmp_path / "big.npz")
    # and the other end: a model that predicts an almost black image cannot be inverted
    at_least = kernels * np.float32(1.001 * MIN_KERNEL_GAIN / MAX_KERNEL_GAIN)
    small = KernelModel(kernels=at_least, basis="si", channels=("L",))   # just above the limit
    assert np.abs(small.kernels).sum() == pytest.approx(MIN_KERNEL_GAIN, rel=2e-3)
    with pytest.raises(ModelFileError, match=r"the largest kernel sums to 9\.\d+e-13"):
        KernelModel(kernels=at_least * np.float32(0.98), basis="si", channels=("L",))


def test_predict_names_the_model_and_the_scenes_when_channels_differ():
    from psfkit.errors import InvalidInputError
    from psfkit.fitting.pairs.fit import predict
    from psfkit.forward.kernelfile import KernelModel

    model = KernelModel(kernels=np.ones((1, 1, 4, 4), np.float32), basis="si",
                        channels=("L",), sensor_shape=(8, 8))
    with pytest.raises(InvalidInputError, match=r"^pairs: scenes have 3 channel\(s\) but the "
                                                r"model mono\.npz has 1 \(L\)$"):
        predict(model, np.ones((1, 3, 8, 8), np.float32), model_name="mono.npz",
                scenes_name="pairs")


def test_photons_below_one_electron_are_refused_by_the_spec_too():
    from ekdun.data.bench_spec import VirtualBenchSpec
    from ekdun.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match=r"photons \(--photons\) must be a number in "
                                                 r"\[1, "):
        VirtualBenchSpec(photons=1e-300)
    assert VirtualBenchSpec(photons=1.0).photons == 1.0


def test_the_true_saturation_level_is_accepted(grid_3x3, tmp_path):
    """The refusals of --saturation-level leave the right value alone: the fixture's 12-bit
    data is stored MSB-aligned in 16 bits, so the sensor clips at 65520."""
    done = _cli("psfkit", "register", str(grid_3x3), "--saturation-level", "65520", "--quiet")
    assert done.returncode == 0, done.stderr
    assert "registered 9 PSFs" in done.stdout


# ------------------------------------------------------------------ found by the sweep


def test_a_closed_stdout_ends_the_command_quietly_after_its_outputs(grid_3x3, tmp_path):
    """``psfkit register GRID --out r.json | head -1``: the reader goes away before the
    summary; the numbers file is complete, and no "error: Broken pipe" (status 2, "nothing
    was written") contradicts it: status 141 (128 + SIGPIPE), as Unix tools."""
    out = tmp_path / "r.json"
    proc = subprocess.Popen([sys.executable, "-m", "psfkit.cli", "register", str(grid_3x3),
                             "--out", str(out), "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=_env(), cwd=REPO)
    proc.stdout.close()                 # before the command prints anything
    err = proc.stderr.read().decode()
    assert proc.wait(300) == 128 + signal.SIGPIPE, err
    assert err == ""
    assert len(json.loads(out.read_text())["positions"]) == 9


def test_a_failed_warp_names_the_position(tmp_path):
    """A position whose PSF leaves no warp field to measure is named in the error line."""
    from psfkit.characterization.characterize import _warp_position
    from psfkit.errors import InvalidInputError

    blank = np.zeros((16, 16), np.float32)
    with pytest.raises(InvalidInputError, match=r"^psf_r00_c00\.tiff: too little of the PSF"):
        _warp_position(blank, blank, np.ones((16, 16), bool), (0.0, 0.0), "dis",
                       "psf_r00_c00.tiff")


def test_a_blank_reference_is_blamed_not_the_black_level(grid_3x3, tmp_path):
    """The black-level check blames the manifest only when the reference capture has a
    signal it would erase; a blank reference capture is still the one refused."""
    import shutil

    import tifffile

    grid = tmp_path / "grid"
    shutil.copytree(grid_3x3, grid, ignore=shutil.ignore_patterns("ground_truth"))
    centre = grid / "psf_r01_c01.tiff"
    tifffile.imwrite(centre, np.zeros_like(tifffile.imread(centre)), photometric="rgb")
    done = _cli("psfkit", "register", str(grid), "--quiet")
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert "psf_r01_c01.tiff" in done.stderr and "black_level" not in done.stderr
