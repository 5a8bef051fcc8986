"""The real training path on DiffuserCam Mirflickr (DLMD) pairs, end to end, on a CPU.

``psfkit fit-pairs`` (shift-invariant PSF, 4× binned) on 6 of the 7 shared pairs, ``ekdun train``
(tiny EK-DUN, 2 epochs) on the DLMD folder with the 7th held out, then ``ekdun reconstruct`` of
that 7th measurement as stored (BGR ``.npy``, 270×480). The reconstruction must be finite, in
RGB and in the ground truth's orientation, and better than the ``Aᵀy`` baseline of the same
kernel file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from ekdun.cli import main as ekdun_main
from ekdun.nets.checkpoint import load_checkpoint
from ekdun.physics import ShiftInvariantOperator
from psfkit.cli import main as psfkit_main
from psfkit.forward.kernelfile import load_kernels
from psfkit.numerics.resample import bin_mean

HELD_OUT = "im65"
FACTOR = 4


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def _ls_scaled(a: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``a`` times the scalar that best fits ``target`` (least squares)."""
    return a * float((a * target).sum() / (a * a).sum())


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _chroma(a: np.ndarray) -> np.ndarray:
    """``(C, H, W)`` minus its per-pixel mean over channels: the colour, not the brightness."""
    return a - a.mean(axis=0, keepdims=True)


def _gradients(a: np.ndarray) -> np.ndarray:
    return np.concatenate([np.diff(a, axis=1).ravel(), np.diff(a, axis=2).ravel()])


@pytest.fixture(scope="module")
def dlmd_fit_folder(real_data, tmp_path_factory) -> tuple[Path, Path]:
    """``(DLMD folder, the same layout without the held-out pair)``: links, not copies."""
    root = real_data("dlmd_mirflickr")
    fit = tmp_path_factory.mktemp("dlmd") / "fit6"
    for sub in ("lensed", "diffuser"):
        (fit / sub).mkdir(parents=True)
        for f in (root / sub).glob("*.npy"):
            if f.stem != HELD_OUT:
                (fit / sub / f.name).symlink_to(f)
    return root, fit


def test_fit_pairs_train_reconstruct_on_dlmd(dlmd_fit_folder, tmp_path, capsys):
    root, fit = dlmd_fit_folder
    kernels = tmp_path / "si.npz"
    assert psfkit_main(["fit-pairs", str(fit), "--basis", "si", "--downsample", str(FACTOR),
                        "--out", str(kernels), "--quiet"]) == 0
    model = load_kernels(kernels)
    assert model.sensor_shape == (270 // FACTOR, 480 // FACTOR)       # 67 x 120, non-square

    # the full folder at full size, with the held-out pair named: the binning comes from the
    # kernel file's provenance, the BGR order from the DLMD layout
    run = tmp_path / "run"
    assert ekdun_main(["train", str(root), str(run), "--network", "ekdun", "--kernels",
                       str(kernels), "--holdout", HELD_OUT, "--epochs", "2",
                       "--batch-size", "2", "--threads", "1", "--quiet"]) == 0
    meta = load_checkpoint(run / "checkpoint.pt")["metadata"]
    assert meta["data"]["holdout"] == [HELD_OUT] and HELD_OUT not in meta["data"]["names"]
    assert len(meta["data"]["names"]) == 6
    assert meta["data"]["channel_order"] == "BGR" and meta["data"]["downsample"] == FACTOR
    assert meta["sensor_shape"] == [67, 120]

    out = tmp_path / "recon"
    measurement = root / "diffuser" / f"{HELD_OUT}.npy"
    assert ekdun_main(["reconstruct", str(run / "checkpoint.pt"), str(measurement),
                       "--out", str(out)]) == 0
    assert (out / f"{HELD_OUT}.png").is_file()
    recon = np.load(out / f"{HELD_OUT}.npy")
    assert recon.shape == (67, 120, 3) and recon.dtype == np.float32
    assert np.all(np.isfinite(recon))
    recon = np.moveaxis(recon, -1, 0).astype(np.float64)

    # ground truth: the stored BGR file, turned to RGB and binned like the model's grid
    truth = bin_mean(np.moveaxis(np.load(root / "lensed" / f"{HELD_OUT}.npy"), -1, 0)[::-1],
                     FACTOR)
    y = bin_mean(np.moveaxis(np.load(measurement), -1, 0)[::-1], FACTOR).astype(np.float32)
    op = ShiftInvariantOperator(torch.as_tensor(model.kernels[0]), model.sensor_shape,
                                model.scene_padding)
    adjoint = op.A_adjoint(torch.from_numpy(y)[None])[0].double().numpy()
    baseline = _psnr(_ls_scaled(adjoint, truth), truth)
    achieved = _psnr(recon, truth)
    print(f"held-out {HELD_OUT}: EK-DUN {achieved:.2f} dB, least-squares scaled A^T y "
          f"{baseline:.2f} dB")
    assert achieved > baseline + 0.25

    # channel order: the colour of the reconstruction follows the RGB truth, not BGR
    assert _corr(_chroma(recon), _chroma(truth)) > _corr(_chroma(recon),
                                                         _chroma(truth[::-1])) + 0.3
    # orientation: its structure lines up with the truth as stored, not a mirrored copy
    edges = _corr(_gradients(recon), _gradients(truth))
    for flipped in (truth[:, ::-1], truth[:, :, ::-1]):
        assert edges > 1.5 * _corr(_gradients(recon), _gradients(flipped))
    assert _corr(recon, truth) > _corr(recon, truth[:, ::-1]) + 0.1

    # ekdun eval on the training folder scores only the held-out pair, read as in training
    assert ekdun_main(["eval", str(run), "--data", str(root), "--out", str(tmp_path / "tables"),
                       "--quiet"]) == 0
    row = json.loads((tmp_path / "tables" / "results.json").read_text())["results"][0]
    print(f"ekdun eval on {row['pairs']}: {row['psnr']:.2f} dB (reconstruct: "
          f"{_psnr(np.clip(recon, 0, 1), truth):.2f} dB)")
    assert row["pairs"] == [HELD_OUT]
    assert abs(row["psnr"] - _psnr(np.clip(recon, 0, 1), truth)) < 0.05


def test_train_refuses_pairs_that_do_not_match_the_kernels(dlmd_fit_folder, tmp_path,
                                                           capsys):
    root, fit = dlmd_fit_folder
    kernels = tmp_path / "si.npz"
    assert psfkit_main(["fit-pairs", str(fit), "--basis", "si", "--downsample", "8",
                        "--iterations", "2", "--out", str(kernels), "--quiet"]) == 0
    capsys.readouterr()
    assert ekdun_main(["train", str(root), str(tmp_path / "run"), "--kernels", str(kernels),
                       "--downsample", "4", "--epochs", "1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "sensor is 33x60" in err and "--downsample 8 matches it" in err, err
    assert ekdun_main(["train", str(root), str(tmp_path / "run"), "--kernels", str(kernels),
                       "--holdout", "im999", "--quiet"]) == 2
    assert "no pair named im999" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
