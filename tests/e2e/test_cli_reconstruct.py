"""``ekdun reconstruct MODEL MEASUREMENT... --out DIR`` for every kind of model (issue 44, item 4).

MODEL is a checkpoint (the network), a kernel file (classical ADMM-TV, as ``ekdun admm
--kernels`` did) or a PSF image (as ``ekdun admm PSF MEASUREMENT`` did). Each form is checked
bit for bit against the library called directly, and against the deprecated spelling, which
still runs and prints one note. ``ekdun train`` writes the learned kernels as a kernel file
that psfkit reads, equal to what the deprecated ``export-kernels`` writes. Each ``--help``
shows at most 12 flags; ``--help-all`` shows every one.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re

import numpy as np
import pytest
import torch

from ekdun.cli import build_parser
from ekdun.cli import main as ekdun_main
from ekdun.cli.classical_cmd import deprecated_note
from ekdun.cli.commands import (
    EVAL_ADVANCED,
    EXPORT_KERNELS_NOTE,
    MAKE_DATASET_ADVANCED,
    TRAIN_ADVANCED,
)
from ekdun.cli.reconstruct_cmd import ADVANCED as RECONSTRUCT_ADVANCED
from ekdun.physics.operators import EigenKernelOperator
from ekdun.reconstruction.classical import (
    ClassicalOptions,
    ModelReconstructor,
    psf_model,
    read_classical_measurement,
)
from psfkit.forward.kernelfile import load_kernels

pytestmark = pytest.mark.e2e

FEW = ["--iterations", "15", "--threads", "1", "--quiet"]   # the classical runs' flags
COMMANDS = {"make-dataset": MAKE_DATASET_ADVANCED, "train": TRAIN_ADVANCED,
            "eval": EVAL_ADVANCED, "reconstruct": RECONSTRUCT_ADVANCED}


def _stderr_lines(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


def _folder(out) -> dict[str, np.ndarray]:
    """``stem -> (C, H, W)`` of an output folder's ``.npy`` files (stored ``H x W x C``)."""
    return {p.stem: np.moveaxis(np.load(p), -1, 0) for p in sorted(out.glob("*.npy"))}


@pytest.fixture(scope="module")
def trained_run(tiny_data, tmp_path_factory):
    """An EK-DUN run folder trained by the CLI (one epoch, two iterations)."""
    pairs, kernels = tiny_data
    run = tmp_path_factory.mktemp("trained") / "run"
    assert ekdun_main(["train", str(pairs), str(run), "--kernels", str(kernels), "--epochs",
                       "1", "--batch-size", "4", "--iterations", "2", "--threads", "1",
                       "--device", "cpu", "--quiet"]) == 0
    return run


# ------------------------------------------------------------------ a kernel file


def test_kernel_file_is_the_library_reference_and_the_admm_spelling(tiny_data, tmp_path,
                                                                    capsys, torch_one_thread):
    pairs, kernels = tiny_data
    out = tmp_path / "rec"
    assert ekdun_main(["reconstruct", str(kernels), str(pairs / "measurement"), "--out",
                       str(out), *FEW]) == 0
    assert _stderr_lines(capsys) == [f"8 reconstruction(s) in {out}"]
    got = _folder(out)
    assert sorted(got) == [f"im{i}" for i in range(8)]
    assert (out / "im0.png").is_file()
    # the library, called directly: the model as fitted, the solver's defaults (tv 3e-4)
    model = load_kernels(kernels)
    recon = ModelReconstructor(model, ClassicalOptions(iterations=15, tv=3e-4))
    op = EigenKernelOperator.from_kernel_model(model, dtype=torch.float64)
    for name, image in got.items():
        y = read_classical_measurement(pairs / "measurement" / f"{name}.npy")
        np.testing.assert_array_equal(image, recon(y).image)
        # and it is a reconstruction: its measurement is closer to y than the adjoint's
        # best-scaled one (the truth of the tiny pairs is y = A x exactly)
        scene = np.moveaxis(np.load(pairs / "scene" / f"{name}.npy"), -1, 0)
        err = np.linalg.norm(image - scene) / np.linalg.norm(scene)
        back = op.A_adjoint(torch.as_tensor(y, dtype=torch.float64)[None])[0].numpy()
        scale = float((back * scene).sum() / (back * back).sum())
        assert err < np.linalg.norm(scale * back - scene) / np.linalg.norm(scene), name
    # the deprecated spellings: the same files, then one note (the last line)
    for spelling in ("admm", "reconstruct-classical"):
        old = tmp_path / spelling
        assert ekdun_main([spelling, "--kernels", str(kernels), str(pairs / "measurement"),
                           "--out", str(old), *FEW]) == 0
        err = _stderr_lines(capsys)
        assert err[-1] == deprecated_note(spelling) and "ekdun reconstruct" in err[-1]
        assert sum("deprecated" in line for line in err) == 1
        for name, image in _folder(old).items():
            np.testing.assert_array_equal(image, got[name])


def test_learned_kernels_of_train_are_a_model_for_reconstruct(tiny_data, trained_run, tmp_path,
                                                              capsys):
    """``ekdun train`` writes RUN/kernels_learned.npz, which psfkit reads: the same kernels as
    the deprecated ``export-kernels`` (with its note), and a MODEL for ``reconstruct``."""
    pairs, kernels = tiny_data
    run = trained_run
    learned = load_kernels(run / "kernels_learned.npz")           # psfkit's reader
    assert learned.kernels.shape == load_kernels(kernels).kernels.shape
    assert not np.array_equal(learned.kernels, load_kernels(kernels).kernels)
    capsys.readouterr()
    exported = tmp_path / "exported.npz"
    assert ekdun_main(["export-kernels", str(run / "checkpoint.pt"), "--out",
                       str(exported)]) == 0
    assert _stderr_lines(capsys)[-1] == EXPORT_KERNELS_NOTE
    again = load_kernels(exported)
    np.testing.assert_array_equal(again.kernels, learned.kernels)
    assert (again.basis, again.convention, again.sensor_shape) == (
        learned.basis, learned.convention, learned.sensor_shape)
    out = tmp_path / "rec"
    assert ekdun_main(["reconstruct", str(run / "kernels_learned.npz"),
                       str(pairs / "measurement" / "im0.npy"), "--out", str(out), *FEW]) == 0
    y = read_classical_measurement(pairs / "measurement" / "im0.npy")
    np.testing.assert_array_equal(
        _folder(out)["im0"], ModelReconstructor(learned, ClassicalOptions(iterations=15))(y).image)


# ------------------------------------------------------------------ a PSF image


@pytest.fixture()
def psf_and_measurements(tmp_path, caustic_psf):
    """A caustic-like RGB PSF image with a background, and two measurements of scenes through
    its shift-invariant model, as ``.npy`` (H, W, C) files (the measurements in a folder)."""
    psf, op, rng = caustic_psf
    folder = tmp_path / "meas"
    folder.mkdir()
    for k in range(2):
        scene = torch.zeros((1, 3, 24, 32), dtype=torch.float64)
        scene[..., 6 + k:18, 8:24 - k] = torch.as_tensor([0.9, 0.5, 0.2 + k / 4],
                                                         dtype=torch.float64)[:, None, None]
        y = op.A(scene)[0].numpy()
        y = y + 0.01 * y.max() * rng.standard_normal(y.shape)
        np.save(folder / f"m{k}.npy", y.transpose(1, 2, 0).astype(np.float32))
    np.save(tmp_path / "psf.npy", psf)
    return tmp_path / "psf.npy", folder


def test_psf_image_is_the_library_reference_and_the_admm_spelling(psf_and_measurements,
                                                                  tmp_path, capsys):
    from psfkit.calibration.psf_image import psf_kernel
    from psfkit.io.images import read_image_float

    psf, folder = psf_and_measurements
    out = tmp_path / "rec"
    assert ekdun_main(["reconstruct", str(psf), str(folder), "--out", str(out), "--tv",
                       "1e-3", *FEW]) == 0
    got = _folder(out)
    assert sorted(got) == ["m0", "m1"]
    # the library: the one PSF treatment (corner background, clipped, unit sum), its SI model
    kernel = psf_kernel(read_image_float(psf), "corner", 1, str(psf))
    model = psf_model(kernel, (24, 32), 3)
    recon = ModelReconstructor(model, ClassicalOptions(iterations=15, tv=1e-3))
    for name, image in got.items():
        y = read_classical_measurement(folder / f"{name}.npy", background="corner")
        np.testing.assert_array_equal(image, recon(y).image)
        capsys.readouterr()
        # the deprecated spelling, one measurement at a time: the same numbers, one note
        single = tmp_path / f"{name}.npy"
        assert ekdun_main(["admm", str(psf), str(folder / f"{name}.npy"), "--out", str(single),
                           "--tv", "1e-3", *FEW]) == 0
        assert _stderr_lines(capsys)[-1] == deprecated_note("admm")
        np.testing.assert_array_equal(np.moveaxis(np.load(single), -1, 0), image)


# (--solver has one solver left: its retired value is tested in test_cli_classical.py)
@pytest.mark.parametrize("flags", [("--no-nonneg",), ("--tol", "0.5"),
                                   ("--dtype", "float64"), ("--background", "none")])
def test_every_advanced_solver_flag_acts(psf_and_measurements, tmp_path, flags):
    psf, folder = psf_and_measurements
    common = [str(psf), str(folder / "m0.npy"), "--tv", "1e-3", *FEW]
    assert ekdun_main(["reconstruct", *common, "--out", str(tmp_path / "d")]) == 0
    assert ekdun_main(["reconstruct", *common, "--out", str(tmp_path / "f"), *flags]) == 0
    default, flagged = np.load(tmp_path / "d" / "m0.npy"), np.load(tmp_path / "f" / "m0.npy")
    assert not np.array_equal(default, flagged), flags
    if flags == ("--no-nonneg",):
        assert flagged.min() < 0 <= default.min()


# ------------------------------------------------------------------ a checkpoint


def test_checkpoint_is_the_library_reference(tiny_data, trained_run, tmp_path, capsys):
    from ekdun.nets.builder import network_from_checkpoint
    from ekdun.nets.checkpoint import load_checkpoint
    from psfkit.io.images import read_image_float

    pairs, kernels = tiny_data
    run = trained_run
    for model, out in ((run / "checkpoint.pt", tmp_path / "a"), (run, tmp_path / "b")):
        assert ekdun_main(["reconstruct", str(model), str(pairs / "measurement"), "--out",
                           str(out), "--device", "cpu"]) == 0
    a, b = _folder(tmp_path / "a"), _folder(tmp_path / "b")       # a run folder: the same
    network, _ = network_from_checkpoint(load_checkpoint(run / "checkpoint.pt"))
    network.eval()
    for name, image in a.items():
        y = read_image_float(pairs / "measurement" / f"{name}.npy")
        with torch.no_grad():
            expected = network(torch.from_numpy(y)[None])[0].numpy()
        np.testing.assert_array_equal(image, expected)
        np.testing.assert_array_equal(b[name], image)
    # a flag of the classical forms is refused with a checkpoint, in one line, before any
    # output; --amp with a kernel file likewise
    capsys.readouterr()
    for bad in (["reconstruct", str(run), str(pairs / "measurement"), "--out",
                 str(tmp_path / "c"), "--tv", "1e-3"],
                ["reconstruct", str(kernels), str(pairs / "measurement"), "--out",
                 str(tmp_path / "c"), "--amp", "bf16"]):
        assert ekdun_main(bad) == 2
        err = _stderr_lines(capsys)
        assert len(err) == 1 and err[0].startswith("ekdun: error: --")
        assert not (tmp_path / "c").exists()


# ------------------------------------------------------------------ a file that is no model


@pytest.mark.parametrize("kind", ["text", "missing", "folder", "corrupt-npz", "corrupt-pt"])
def test_a_file_that_is_no_model_is_one_line_naming_it(tiny_data, tmp_path, capsys, kind):
    pairs, _ = tiny_data
    model = {"text": tmp_path / "notes.txt", "missing": tmp_path / "nothing.npz",
             "folder": tmp_path / "empty", "corrupt-npz": tmp_path / "bad.npz",
             "corrupt-pt": tmp_path / "bad.pt"}[kind]
    if kind == "folder":
        model.mkdir()
    elif kind != "missing":
        model.write_text("not a model")
    out = tmp_path / "rec"
    assert ekdun_main(["reconstruct", str(model), str(pairs / "measurement"), "--out",
                       str(out)]) == 2
    err = _stderr_lines(capsys)
    assert len(err) == 1 and err[0].startswith("ekdun: error:") and str(model) in err[0], err
    assert not out.exists()


# ------------------------------------------------------------------ the help screens


def _help(argv: list[str]) -> str:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit) as done:
        build_parser().parse_args(argv)
    assert done.value.code == 0
    return buf.getvalue()


def _flag_lines(text: str) -> list[str]:
    """The flags of a help screen: the lines that start with an option."""
    return re.findall(r"^ {2}(-[-\w]+)", text, flags=re.M)


def test_four_user_commands_and_short_help_screens():
    listed = re.findall(r"^ {4}([a-z][a-z-]+)", _help(["--help"]).split("commands:")[1],
                        flags=re.M)
    assert listed == ["make-dataset", "train", "eval", "reconstruct"]
    sub = next(a for a in build_parser()._actions
               if isinstance(a, argparse._SubParsersAction))
    for command, advanced in COMMANDS.items():
        short, full = _help([command, "--help"]), _help([command, "--help-all"])
        shown, every = _flag_lines(short), _flag_lines(full)
        assert len(shown) <= 12 and "--help-all" in shown, (command, shown)
        assert not set(advanced) & set(shown), (command, shown)
        usage = short.split("\n\n")[0]
        assert not any(re.search(rf"\[{re.escape(a)}[\] ]", usage) for a in advanced), usage
        # --help-all: every flag of the command but the hidden deprecated/retired spellings
        flags = {a.option_strings[0] for a in sub.choices[command]._actions
                 if a.option_strings and (a.help != argparse.SUPPRESS
                                          or a.option_strings[0] in advanced)}
        assert set(every) == flags, (command, set(every) ^ flags)
        assert len(every) == len(shown) + len(advanced)
