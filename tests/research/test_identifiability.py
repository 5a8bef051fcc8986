"""Identifiability in numbers (issue 23, item 4): the Monte-Carlo spread of the fitted
difference kernels follows the noise model, and the Fisher (Cramér–Rao) prediction agrees with
it on a small eigen-kernel model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from psfkit.fitting.pairs.batches import PairBatches
from psfkit.fitting.pairs.fit import predict
from psfkit.forward.kernelfile import KernelModel
from research.identifiability import (
    difference_fisher,
    fit_unconstrained,
    monte_carlo,
    noise_variance,
    poisson_gaussian,
)

SHAPE = (32, 32)


def _model() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A one-channel paper-basis eigen-kernel model (source side), its scenes (dead leaves),
    their noise-free measurements and the noise-free fit."""
    from scipy.ndimage import shift

    from ekdun.data.bench_spec import VirtualBenchSpec, make_scenes
    from research.synthetic import caustic_psf

    base = caustic_psf(SHAPE, 1, seed=3).astype(np.float64)
    base /= base.sum()
    kernels = np.stack([base, shift(base, (0, 0.6, 0), order=1),
                        shift(base, (0, 0, 0.6), order=1)])
    scenes = make_scenes(VirtualBenchSpec(sensor_shape=SHAPE, n_train=8, n_test=1,
                                          natural_fraction=0.0),
                         "train")[:, :1].astype(np.float64)
    model = KernelModel(kernels=kernels.astype(np.float32), basis="paper",
                        convention="source", sensor_shape=SHAPE, channels=("L",))
    clean = predict(model, scenes, dtype=torch.float64)
    return kernels, scenes, clean, fit_unconstrained(scenes, clean, "paper", "source")


@pytest.fixture(scope="module")
def model() -> tuple[np.ndarray, ...]:
    return _model()


def test_noise_model_has_the_stated_variance() -> None:
    clean = np.full((4, 1, 64, 64), 0.3)
    for photons in (100.0, 10000.0):
        noisy = poisson_gaussian(clean, photons, 2.0, np.random.default_rng(0))
        measured = float(np.var(noisy - clean))
        expected = noise_variance(clean, photons, 2.0)
        assert measured == pytest.approx(expected, rel=0.05)


def test_spread_shrinks_as_photons_grow(model: tuple[np.ndarray, ...]) -> None:
    """Variance of the difference kernels ∝ 1/P (Poisson, no read noise): 100× more photons,
    100× less variance (10× less spread); the displacement maps get tighter too."""
    kernels, scenes, clean, clean_fit = model
    low = monte_carlo(scenes, clean, kernels, 1e3, 0.0, draws=3, seed=1, clean_fit=clean_fit)
    high = monte_carlo(scenes, clean, kernels, 1e5, 0.0, draws=3, seed=2, clean_fit=clean_fit)
    for k in ("v", "h"):
        ratio = low.metrics[k]["kernel_sq"] / high.metrics[k]["kernel_sq"]
        assert 60 < ratio < 160, (k, ratio)
        spread_ratio = low.metrics[k]["kernel_spread"] / high.metrics[k]["kernel_spread"]
        assert 7.5 < spread_ratio < 13, (k, spread_ratio)
        assert high.metrics[k]["disp_spread_px"] < low.metrics[k]["disp_spread_px"]
        assert high.metrics[k]["ncc"] > low.metrics[k]["ncc"]
        assert low.metrics[k]["bias"] == high.metrics[k]["bias"]      # noise-free: no P


def test_fisher_bound_predicts_the_monte_carlo(model: tuple[np.ndarray, ...]) -> None:
    """The no-crop Cramér–Rao bound and the measured variance agree to a factor of 2 (the
    crop, the kernel window and the Poisson noise are what it leaves out)."""
    kernels, scenes, clean, clean_fit = model
    photons = 1e4
    sigma2 = noise_variance(clean, photons, 0.0)
    fisher = difference_fisher(PairBatches(scenes, "paper", "source", SHAPE), sigma2)
    assert 0 < fisher["eig_min"] <= fisher["eig_median"] <= fisher["eig_max"]
    mc = monte_carlo(scenes, clean, kernels, photons, 0.0, draws=4, seed=4,
                     clean_fit=clean_fit)
    for k in ("v", "h"):
        ratio = mc.metrics[k]["kernel_sq"] / fisher["crb_sq"][k]
        assert 0.5 < ratio < 2.0, (k, ratio)
