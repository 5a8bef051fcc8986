# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 4. Real data: forward models fitted to DiffuserCam (DLMD) pairs
#
# Without a PSF grid, a forward model can still be fitted to (scene, measurement) pairs:
# `psfkit.fitting.pairs.fit` solves for the kernels that best predict the measurements from the
# scenes (a regularised least-squares fit by conjugate gradients). Does the paper's
# eigen-kernel model (`Kbase`, `Kv`, `Kh`) predict *held-out* measurements better than one
# shift-invariant PSF? We answer with leave-one-out errors on the few DLMD (MirFlickr) pairs
# shipped with the project's shared data.
#
# The data are looked up in `$EKDUN_SHARED_DATA` (or `$PSFKIT_SHARED_DATA`), else in
# `shared/data` next to the repository. If they are absent the notebook says so and stops.
#
# For speed the pairs are binned 4× (67 × 120 px), the solver runs 15 conjugate-gradient
# iterations in one round (the library defaults are 60 and 3), and the eigen-kernel fit starts
# from the shift-invariant one (`initial=`), which it then only has to correct. Set
# `EKDUN_NB_DOWNSAMPLE=2` for the 135 × 240 version (several minutes on two cores) and
# `EKDUN_NB_HELD_OUT=N` to hold out only the first N pairs (CI does, to save time).

# %%
import os
from pathlib import Path

import numpy as np
from IPython.display import display

import psfkit
from psfkit.fitting.pairs.fit import PairFitOptions, fit_pairs, predict, relative_errors
from psfkit.io import read_pairs
from psfkit.report.figures import figure_kernels
from psfkit.report.figures.style import new_figure


def shared_data() -> Path:
    """The shared data folder: environment variable, else ``<repo>/../shared/data``."""
    for var in ("EKDUN_SHARED_DATA", "PSFKIT_SHARED_DATA"):
        if os.environ.get(var):
            return Path(os.environ[var])
    return Path(psfkit.__file__).resolve().parents[1].parent / "shared" / "data"


PAIRS = shared_data() / "dlmd_mirflickr"
HAVE_DATA = PAIRS.is_dir()
DOWNSAMPLE = int(os.environ.get("EKDUN_NB_DOWNSAMPLE", "4"))
HELD_OUT = int(os.environ.get("EKDUN_NB_HELD_OUT", "0"))  # 0: every pair
OPTIONS = {"iterations": 15, "rounds": 1}
if HAVE_DATA:
    print("pairs:", PAIRS)
else:
    print(f"The DLMD pairs are not available ({PAIRS} does not exist): set EKDUN_SHARED_DATA "
          "to the folder holding dlmd_mirflickr/. Nothing more to do in this notebook.")

# %% [markdown]
# ## Read and bin the pairs
# `read_pairs` knows the DLMD layout (`lensed/` scenes, `diffuser/` measurements, BGR files)
# and returns RGB `(N, C, H, W)` arrays.


# %%
def binned(a: np.ndarray, f: int) -> np.ndarray:
    n, c, h, w = a.shape
    a = a[..., :h // f * f, :w // f * f]
    return a.reshape(n, c, h // f, f, w // f, f).mean(axis=(3, 5)).astype(np.float32)


if HAVE_DATA:
    pairs = read_pairs(PAIRS)
    scenes, measurements = pairs.load_all()
    scenes, measurements = binned(scenes, DOWNSAMPLE), binned(measurements, DOWNSAMPLE)
    print(len(pairs), "pairs,", scenes.shape[1:], "after binning", DOWNSAMPLE)

# %% [markdown]
# ## Fit a shift-invariant PSF and the paper's eigen-kernel model to all pairs
# The eigen-kernel fit starts from three copies of the shift-invariant PSF.


# %%
def fit_both(x: np.ndarray, y: np.ndarray) -> dict:
    """Shift-invariant fit, then the paper's model seeded with it."""
    si = fit_pairs(x, y, PairFitOptions(basis="si", tikhonov=0.0, **OPTIONS))
    # seven real pairs do not determine Kv - Kbase and Kh - Kbase on their own: the difference
    # prior (fit-pairs --difference 1) keeps them near Kbase where the data are silent
    paper = fit_pairs(x, y, PairFitOptions(basis="paper", difference=1.0, **OPTIONS),
                      initial=np.repeat(si.kernels, 3, axis=0))
    return {"si": si, "paper": paper}


if HAVE_DATA:
    fits = fit_both(scenes, measurements)
    for basis, fit in fits.items():
        train = relative_errors(predict(fit.kernel_model(), scenes), measurements)
        print(f"{basis:6s} training relative error (scaled) {train['scaled'].mean():.4f}")
    display(figure_kernels(fits["paper"].kernels, fits["paper"].kernel_model().kernel_names,
                           "eigen-kernels fitted to the DLMD pairs"))

# %% [markdown]
# ## Held-out errors: leave one pair out
# Each pair is predicted by the model fitted to the other pairs. "scaled" allows one unknown
# brightness factor per image (the ground-truth scenes are normalised per image).

# (`psfkit.fitting.pairs.fit.leave_one_out` does the same for one basis; here each fold also seeds
# the eigen-kernel fit with its own shift-invariant fit.)

# %%
held_out = {"si": [], "paper": []}
if HAVE_DATA:
    count = HELD_OUT or len(scenes)
    for i in range(count):
        keep = np.arange(len(scenes)) != i
        fold = fit_both(scenes[keep], measurements[keep])
        for basis, fit in fold.items():
            err = relative_errors(predict(fit.kernel_model(), scenes[i:i + 1]),
                                  measurements[i:i + 1])
            held_out[basis].append(float(err["scaled"][0]))
    for basis, errors in held_out.items():
        print(f"{basis:6s} held-out relative error: mean {np.mean(errors):.4f} "
              f"(per pair {np.round(errors, 3)})")

# %%
if HAVE_DATA:
    fig = new_figure(3.5, 2.4)
    ax = fig.subplots()
    index = np.arange(len(held_out["si"]))
    for offset, basis in ((-0.2, "si"), (0.2, "paper")):
        ax.bar(index + offset, held_out[basis], width=0.4, label=basis)
    ax.set_xlabel("held-out pair")
    ax.set_ylabel("relative error (scaled)")
    ax.legend(frameon=False)
    display(fig)

# %% [markdown]
# With a handful of pairs the three-kernel model has three times the unknowns of one PSF: it
# fits the training pairs better, but whether it also predicts held-out pairs better is what
# the leave-one-out numbers above say. When it does not, the extra kernels fit noise
# (over-fitting): more pairs, a stronger `difference` prior, or kernels seeded from a PSF grid
# (`psfkit fit-eigen`) are the remedies.

# %% [markdown]
# ## Reconstruct an unseen measurement with the fitted models (no training)
# `ekdun admm --kernels` as a library call. Each model is fitted with the library defaults (as
# `psfkit fit-pairs` does: non-negative kernels) on six pairs, and the seventh (`im65`) is
# reconstructed by ADMM-TV with the model as fitted: one PSF, and the paper's eigen-kernel
# model with source-side weights (the weights multiply the scene: each scene point has its own
# PSF). Both solve for the scene on the padded grid, so light from outside the view does not
# turn into artefacts at the borders; the source-side model's weights keep their edge values
# out there. PSNR after a least-squares brightness scale, as in the benchmark.

# %%
from ekdun.reconstruction import ClassicalOptions, ModelReconstructor

CLASSICAL_PAIR = "im65"


def scaled_psnr(image: np.ndarray, truth: np.ndarray) -> float:
    """PSNR (dB) after the least-squares scale onto ``truth``, clipped to [0, 1]."""
    a = float((image * truth).sum() / (image * image).sum())
    return float(10 * np.log10(1.0 / np.mean((np.clip(a * image, 0, 1) - truth) ** 2)))


if HAVE_DATA:
    i = pairs.names.index(CLASSICAL_PAIR)
    rest = [j for j in range(len(scenes)) if j != i]
    classical = {}
    for label, fit_options in (("SI", PairFitOptions(basis="si", tikhonov=0.0)),
                               ("EK, source side", PairFitOptions(basis="paper",
                                                                  convention="source",
                                                                  difference=1.0))):
        model = fit_pairs(scenes[rest], measurements[rest], fit_options).kernel_model()
        classical[label] = ModelReconstructor(model, ClassicalOptions(tv=1e-4))(measurements[i])
    fig = new_figure(5.4, 1.6)
    for k, (label, result) in enumerate(classical.items()):
        ax = fig.add_subplot(1, 3, k + 1)
        image = result.image / result.image.max()
        ax.imshow(np.clip(np.moveaxis(image, 0, -1), 0, 1))
        ax.set_title(f"{label}: {scaled_psnr(result.image, scenes[i]):.2f} dB, "
                     f"{result.seconds:.2f} s", fontsize=7)
        ax.axis("off")
    ax = fig.add_subplot(1, 3, 3)
    ax.imshow(np.clip(np.moveaxis(scenes[i], 0, -1), 0, 1))
    ax.set_title("ground truth", fontsize=7)
    ax.axis("off")
    display(fig)
    print(f"classical {CLASSICAL_PAIR}: " + ", ".join(
        f"{label} {scaled_psnr(result.image, scenes[i]):.2f} dB"
        for label, result in classical.items()))

# %% [markdown]
# One pair says little. `benchmarks/bench_real_reconstruction.py` does this for every pair in
# turn (leave-one-out), chooses each method's TV weight and iteration count on two of the fit
# pairs only, and adds LenslessPiCam's ADMM with the same SI PSF as a peer; its measured tables
# (at this notebook's size and larger, with the machine they were measured on) are in
# [docs/reconstruction.md](../docs/reconstruction.md), and are not repeated here: a number in
# a notebook should be one the notebook computes.

# %% [markdown]
# ## From the pairs to a trained network and a reconstruction of an unseen measurement
# The same path as `psfkit fit-pairs` → `ekdun train` → `ekdun reconstruct`
# ([docs/your-camera.md](../docs/your-camera.md)), as library calls and at CPU size: one pair
# (`im65`) is held out, a shift-invariant PSF is fitted to the other six at the notebook's
# binning, a tiny EK-DUN trains for 2 epochs on the six pairs (read at full size and binned
# like the fit: the binning comes with `PairsDataset(downsample=...)`), and the held-out
# measurement is reconstructed straight from its BGR `.npy` file. The reconstruction comes out
# in RGB and in the orientation of the stored ground truth (the lensed and diffuser images of
# DLMD share one orientation; the upstream `flipud` is for display only). It is compared
# with the `Aᵀy` baseline of the same kernels, scaled by least squares. With six training
# pairs and two epochs the network barely leaves its physics-only initialisation: expect a
# fraction of a dB over `Aᵀy`, not a sharp image.

# %%
import torch

from ekdun.data.pairs import PairsDataset
from ekdun.physics import ShiftInvariantOperator
from ekdun.reconstruction import reconstruct_files
from ekdun.training import TrainOptions, train

NB_OUT = Path(os.environ.get("EKDUN_NB_OUT", "notebook_outputs")) / "04_dlmd_training"
TEST_PAIR = "im65"


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


if HAVE_DATA:
    torch.manual_seed(0)
    train_set = PairsDataset(PAIRS, holdout=[TEST_PAIR], downsample=DOWNSAMPLE)
    keep = [pairs.names.index(n) for n in train_set.names]
    psf_fit = fit_pairs(scenes[keep], measurements[keep],
                        PairFitOptions(basis="si", tikhonov=0.0, **OPTIONS))
    kernel_model = psf_fit.kernel_model({"downsample": DOWNSAMPLE})
    run = train(NB_OUT / "run", "ekdun", kernel_model, train_set, "tiny",
                options=TrainOptions(epochs=2, batch_size=2, progress=False, threads=1),
                overwrite=True)
    print("trained on", ", ".join(train_set.names), "- epoch losses",
          [round(h["train_loss"], 4) for h in run["history"]])
    reconstruct_files(NB_OUT / "run" / "checkpoint.pt",
                      [PAIRS / "diffuser" / f"{TEST_PAIR}.npy"], NB_OUT / "recon",
                      overwrite=True)
    recon = np.moveaxis(np.load(NB_OUT / "recon" / f"{TEST_PAIR}.npy"), -1, 0)
    truth = scenes[pairs.names.index(TEST_PAIR)].astype(np.float64)
    y_test = measurements[pairs.names.index(TEST_PAIR)]
    op = ShiftInvariantOperator(torch.as_tensor(psf_fit.kernels[0]), kernel_model.sensor_shape)
    back = op.A_adjoint(torch.from_numpy(y_test)[None])[0].double().numpy()
    back = back * (back * truth).sum() / (back * back).sum()
    print(f"held-out {TEST_PAIR}: EK-DUN {psnr_db(recon, truth):.2f} dB, "
          f"least-squares scaled Aᵀy {psnr_db(back, truth):.2f} dB")
    fig = new_figure(7.0, 1.6)
    for k, (title, image) in enumerate((("measurement (RGB)", y_test / y_test.max()),
                                        ("Aᵀy (scaled)", back), ("EK-DUN", recon),
                                        ("ground truth", truth))):
        ax = fig.add_subplot(1, 4, k + 1)
        ax.imshow(np.clip(np.moveaxis(image, 0, -1), 0, 1))
        ax.set_title(title, fontsize=7)
        ax.axis("off")
    display(fig)
