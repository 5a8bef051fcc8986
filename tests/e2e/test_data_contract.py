"""One data contract from file to number (issue 21): the same pairs stored as ``.npy``, 8-bit
PNG and 16-bit TIFF give the same numbers from every command, and a model's recorded read
options are applied by the commands that consume it.

The seven DiffuserCam Mirflickr (DLMD) pairs of ``../shared/data`` are quantised once to 8 bits
(``q = round(255 · clip(v, 0, 1))``) and stored three ways, RGB (declared in ``pairs.json``),
``scene/`` + ``measurement/``:

- ``npy``: float32 ``q / 255``;
- ``png8``: ``q`` as 8-bit PNG;
- ``tiff16``: ``257 · q`` as 16-bit TIFF (``257 · q / 65535 = q / 255`` exactly).

Integer files are divided by their dtype's maximum in float32, which is correctly rounded, so all
three folders read as the same float32 arrays, bit for bit (asserted), and every command must
then give the same result up to the run-to-run spread of one machine (it is exact here: same
inputs, same code, same threads; the tolerances only guard against a nondeterministic FFT
plan). Against the original float pairs the numbers agree within the quantisation error
(measured: about 1e-3 on the relative prediction errors of ~0.05), while a unit error (integer
files left unscaled: the 255× bug) moves them by orders of magnitude.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ekdun.cli import main as ekdun_main
from psfkit.cli import main as psfkit_main
from psfkit.forward.kernelfile import load_kernels
from psfkit.io import read_pairs, write_image

FACTOR = 4
FORMATS = {"npy": ".npy", "png8": ".png", "tiff16": ".tif"}


def _store(q: np.ndarray, fmt: str) -> np.ndarray:
    """8-bit levels ``q`` ``(C, H, W)`` as the array a file of format ``fmt`` stores."""
    if fmt == "npy":
        return q.astype(np.float32) / np.float32(255)
    if fmt == "png8":
        return q
    return q.astype(np.uint16) * np.uint16(257)


@pytest.fixture(scope="module")
def dlmd(real_data) -> Path:
    return real_data("dlmd_mirflickr")


@pytest.fixture(scope="module")
def variants(dlmd, tmp_path_factory) -> dict[str, Path]:
    """The DLMD pairs quantised to 8 bits, as ``.npy``, PNG-8 and TIFF-16 folders (RGB)."""
    pairs = read_pairs(dlmd)                   # the DLMD layout: BGR .npy, read as RGB
    root = tmp_path_factory.mktemp("formats")
    folders = {}
    for fmt, suffix in FORMATS.items():
        folder = root / fmt
        for i, name in enumerate(pairs.names):
            scene, measurement = pairs.load(i)
            for sub, image in (("scene", scene), ("measurement", measurement)):
                q = np.rint(np.clip(image, 0, 1) * 255).astype(np.uint8)
                (folder / sub).mkdir(parents=True, exist_ok=True)
                write_image(folder / sub / f"{name}{suffix}", _store(q, fmt))
        # declared, as a user should: a model fitted on the BGR originals records BGR, and
        # that record is what an undeclared folder of .npy/TIFF files would be read with
        (folder / "pairs.json").write_text(json.dumps({"channel_order": "RGB"}))
        folders[fmt] = folder
    return folders


def test_the_three_formats_read_as_the_same_float32_arrays(variants):
    loaded = {fmt: read_pairs(folder).load_all() for fmt, folder in variants.items()}
    scenes, measurements = loaded["npy"]
    assert scenes.dtype == np.float32 and 0 <= scenes.min() and scenes.max() <= 1
    assert measurements.max() > 0.2                       # DLMD raw data peaks near 0.36
    for fmt in ("png8", "tiff16"):
        assert loaded[fmt][0].dtype == np.float32
        np.testing.assert_array_equal(loaded[fmt][0], scenes, err_msg=fmt)
        np.testing.assert_array_equal(loaded[fmt][1], measurements, err_msg=fmt)


def _fit(pairs: Path, out: Path, *extra: str) -> dict:
    report = out.with_suffix(".json")
    assert psfkit_main(["fit-pairs", str(pairs), "--basis", "si", "--downsample", str(FACTOR),
                        "--iterations", "20", "--projected-iterations", "20",
                        "--out", str(out), "--report", str(report), "--quiet", *extra]) == 0
    return json.loads(report.read_text())


def _eval_model(model: Path, pairs: Path, out: Path) -> dict:
    assert psfkit_main(["eval-model", str(model), str(pairs), "--out", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def fits(variants, dlmd, tmp_path_factory) -> dict[str, tuple[Path, dict]]:
    """``psfkit fit-pairs`` (SI, 4× binned) of every format and of the original float pairs."""
    root = tmp_path_factory.mktemp("fits")
    out = {}
    for name, folder in {**variants, "float": dlmd}.items():
        kernels = root / f"{name}.npz"
        out[name] = kernels, _fit(folder, kernels)
    return out


def test_fit_pairs_gives_the_same_kernels_and_errors_from_every_format(fits):
    reference = load_kernels(fits["npy"][0])
    errors = np.array(list(fits["npy"][1]["training_error"].values()))
    for fmt in ("png8", "tiff16"):
        model = load_kernels(fits[fmt][0])
        np.testing.assert_allclose(model.kernels, reference.kernels, rtol=0,
                                   atol=1e-6 * float(np.abs(reference.kernels).max()))
        np.testing.assert_allclose(list(fits[fmt][1]["training_error"].values()), errors,
                                   rtol=1e-5)
        # the read options recorded for the model's users: RGB files, binned 4x, no white level
        assert model.read_options.to_json() == {"channel_order": "RGB", "flip": "none",
                                                "downsample": FACTOR, "white_level": None}
    # the same pairs in float: within the 8-bit quantisation error, not 255x off
    float_errors = np.array(list(fits["float"][1]["training_error"].values()))
    assert np.all(np.abs(errors - float_errors) < 0.01), (errors, float_errors)
    assert load_kernels(fits["float"][0]).read_options.channel_order == "BGR"   # DLMD layout


def test_eval_model_gives_the_same_numbers_on_every_format(fits, variants, tmp_path):
    # the model fitted on the original float pairs, evaluated on each stored format
    model = fits["float"][0]
    results = {fmt: _eval_model(model, folder, tmp_path / f"{fmt}.json")
               for fmt, folder in variants.items()}
    for fmt in ("png8", "tiff16"):
        for name, row in results["npy"]["per_pair"].items():
            assert results[fmt]["per_pair"][name]["raw"] == pytest.approx(row["raw"], rel=1e-5)
            assert results[fmt]["per_pair"][name]["scaled"] == pytest.approx(row["scaled"],
                                                                             rel=1e-5)
        assert results[fmt]["downsample"] == FACTOR           # from the kernel file's record
    # and on the float originals, within quantisation: integer files are in the same units
    original = _eval_model(model, fits["float"][1]["pairs"], tmp_path / "float.json")
    assert results["npy"]["mean_raw"] == pytest.approx(original["mean_raw"], abs=0.01)


@pytest.fixture(scope="module")
def checkpoint(fits, variants, tmp_path_factory) -> Path:
    """A tiny EK-DUN trained 1 epoch on the ``.npy`` format, seeded by its SI fit."""
    run = tmp_path_factory.mktemp("train") / "run"
    assert ekdun_main(["train", str(variants["npy"]), str(run), "--kernels",
                       str(fits["npy"][0]), "--epochs", "1", "--batch-size", "4",
                       "--iterations", "2", "--threads", "1", "--seed", "0", "--quiet"]) == 0
    return run / "checkpoint.pt"


def test_ekdun_eval_gives_the_same_psnr_on_every_format(checkpoint, variants, tmp_path):
    psnr, ssim = {}, {}
    for fmt, folder in variants.items():
        out = tmp_path / fmt
        assert ekdun_main(["eval", str(checkpoint), "--data", str(folder), "--out", str(out),
                           "--include-training", "--quiet"]) == 0
        rows = json.loads((out / "results.json").read_text())["results"]
        assert len(rows) == 1 and len(rows[0]["pairs"]) == 7, rows
        psnr[fmt], ssim[fmt] = rows[0]["psnr"], rows[0]["ssim"]
    assert 5 < psnr["npy"] < 40 and 0 < ssim["npy"] < 1, psnr      # in [0, 1] units, not -43 dB
    for fmt in ("png8", "tiff16"):
        assert psnr[fmt] == pytest.approx(psnr["npy"], abs=1e-4), psnr
        assert ssim[fmt] == pytest.approx(ssim["npy"], abs=1e-5), ssim


def test_reconstructions_are_the_same_from_every_format(checkpoint, fits, variants, tmp_path):
    learned, classical = {}, {}
    for fmt, folder in variants.items():
        out = tmp_path / f"net-{fmt}"
        assert ekdun_main(["reconstruct", str(checkpoint), str(folder / "measurement"),
                           "--out", str(out)]) == 0
        learned[fmt] = np.stack([np.load(f) for f in sorted(out.glob("*.npy"))])
        out = tmp_path / f"admm-{fmt}"
        # the kernel file records the 4x binning: full-size measurements are binned by default
        assert ekdun_main(["reconstruct", str(fits["npy"][0]),
                           str(folder / "measurement"), "--out", str(out), "--iterations",
                           "20", "--quiet"]) == 0
        classical[fmt] = np.stack([np.load(f) for f in sorted(out.glob("*.npy"))])
    assert learned["npy"].shape == (7, 270 // FACTOR, 480 // FACTOR, 3)
    assert classical["npy"].shape == learned["npy"].shape
    for fmt in ("png8", "tiff16"):
        for name, result in (("reconstruct CKPT", learned), ("reconstruct KERNELS", classical)):
            scale = float(np.abs(result["npy"]).max())
            np.testing.assert_allclose(result[fmt], result["npy"], rtol=0, atol=1e-5 * scale,
                                       err_msg=f"{name} {fmt}")


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    a = a * float((a * b).sum() / (a * a).sum())        # best scale: units differ by the model
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def test_reconstruct_reads_a_dlmd_measurement_as_its_kernel_file_records(fits, dlmd, tmp_path,
                                                                         capfd):
    """A kernel file fitted on the DLMD pairs (BGR .npy, binned 4x) reconstructs a bare DLMD
    measurement correctly without flags: the same result as with the explicit flags, and
    better than reading it as RGB (which is refused silently no more: a notice says so)."""
    model, name = fits["float"][0], "im394"
    measurement = dlmd / "diffuser" / f"{name}.npy"

    def recon(tag: str, *flags: str) -> np.ndarray:
        out = tmp_path / tag
        assert ekdun_main(["reconstruct", str(model), str(measurement), "--out",
                           str(out), "--iterations", "30", "--quiet", *flags]) == 0
        return np.moveaxis(np.load(out / f"{name}.npy"), -1, 0)

    capfd.readouterr()
    default = recon("default")
    assert "note:" not in capfd.readouterr().err
    explicit = recon("explicit", "--channel-order", "BGR", "--downsample", str(FACTOR))
    np.testing.assert_array_equal(default, explicit)
    swapped = recon("rgb", "--channel-order", "RGB")
    notice = [line for line in capfd.readouterr().err.splitlines() if line.startswith("note:")]
    assert len(notice) == 1 and "--channel-order RGB" in notice[0] and "BGR" in notice[0]

    # ground truth: the lensed image, read as the pairs are (BGR -> RGB), binned like the model
    pairs = read_pairs(dlmd)
    truth = pairs.load(pairs.names.index(name))[0]
    from psfkit.numerics.resample import bin_mean

    truth = bin_mean(truth, FACTOR)
    assert default.shape == truth.shape
    assert _psnr(default, truth) > _psnr(swapped, truth) + 0.3, \
        (_psnr(default, truth), _psnr(swapped, truth))
