"""research/baseline_checks.py (issue 45): the field-free bench is one convolution plus the
bench's noise, and the sweep, field-free and overfitting checks run and report what they
measured."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.signal import fftconvolve

from ekdun.data.pairs import PairsDataset
from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench
from ekdun.nets.configs import UNetConfig, get_preset
from ekdun.nets.unet import UNet
from ekdun.training.trainer import TrainOptions
from research import baseline_checks as bc

pytestmark = [pytest.mark.e2e, pytest.mark.slow]
QUIET = TrainOptions(epochs=1, progress=False, threads=1)
RECIPE = get_preset("tiny").training_for("updn").lr      # UPDN's own learning rate


def _noise_ratio(measured: np.ndarray, clean: np.ndarray, spec: VirtualBenchSpec) -> float:
    """Mean squared residual over the Poisson–Gaussian variance the bench draws."""
    variance = np.clip(clean, 0, None) / spec.photons + (spec.read_noise_e / spec.photons) ** 2
    return float(np.mean((measured - clean) ** 2) / np.mean(variance))


def test_field_free_pairs_are_the_centre_psf_convolution_plus_the_bench_noise(tmp_path):
    spec = VirtualBenchSpec(sensor_shape=(32, 32), n_train=4, n_test=2)
    root = bc.make_field_free_pairs(tmp_path / "ff", spec)
    psf = np.load(root / "centre_psf.npy")
    pairs = PairsDataset(root / "train")
    varying = PairsDataset(make_virtual_bench(tmp_path / "bench", spec, progress=False)
                           / "train")
    h, w = spec.sensor_shape
    ratios, varying_ratios = [], []
    for i in range(len(pairs)):
        x, y = (t.numpy().astype(np.float64) for t in pairs[i])
        # an independent linear convolution, the PSF's origin at its centre pixel
        clean = np.stack([fftconvolve(x[c], psf[c])[h // 2:h // 2 + h, w // 2:w // 2 + w]
                          for c in range(3)])
        ratios.append(_noise_ratio(y, clean, spec))
        xv, yv = (t.numpy().astype(np.float64) for t in varying[i])
        np.testing.assert_array_equal(xv, x)                   # the bench's own scenes
        varying_ratios.append(_noise_ratio(yv, clean, spec))
    # 4 × 3 × 32² residuals: the ratio's sampling spread is about 1.3 %
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.08)
    # the varying bench's measurements are far from one convolution: the check means something
    assert np.mean(varying_ratios) > 5


def test_field_free_check_pairs_each_network_with_ekdun_base_only_by_seed(tmp_path):
    spec = VirtualBenchSpec(sensor_shape=(16, 16), n_train=4, n_test=2)
    doc = bc.field_free_check(tmp_path, spec, [0, 1], QUIET, networks=("ekdun-base", "updn"),
                              log=lambda text: None)
    assert [(r["label"], r["seed"]) for r in doc["rows"]] == [
        ("EK-DUN (base)", 0), ("UPDN", 0), ("EK-DUN (base)", 1), ("UPDN", 1)]
    psnr = {(r["label"], r["seed"]): r["psnr"] for r in doc["rows"]}
    gaps = [psnr[("UPDN", s)] - psnr[("EK-DUN (base)", s)] for s in (0, 1)]
    assert doc["updn_minus_base_db"] == pytest.approx(np.mean(gaps))
    assert doc["updn_within_margin"] == (abs(np.mean(gaps)) <= bc.FIELD_FREE_MARGIN_DB)
    # each network trained with its own recipe, at the same budget
    assert {r["lr"] for r in doc["rows"] if r["label"] == "UPDN"} == {RECIPE}
    assert {r["epochs"] for r in doc["rows"]} == {1}
    assert "Δ PSNR to EK-DUN base only" in (tmp_path / "field_free.md").read_text()


def test_sweep_reports_the_recipe_against_the_best_rate(tmp_path):
    spec = VirtualBenchSpec(sensor_shape=(16, 16), n_train=4, n_test=2)
    doc = bc.lr_sweep(tmp_path, spec, ["updn"], [1e-3, RECIPE], [0], QUIET,
                      log=lambda text: None)
    by_lr = {r["lr"]: r["psnr"] for r in doc["rows"]}
    summary = doc["summary"]["updn"]
    assert summary["best_lr"] == max(by_lr, key=by_lr.get)
    assert summary["recipe_lr"] == RECIPE
    assert summary["recipe_gap_db"] == pytest.approx(by_lr[RECIPE] - max(by_lr.values()))
    back = json.loads((tmp_path / "sweep.json").read_text())
    assert back["summary"]["updn"]["best_lr"] == summary["best_lr"]


def test_every_network_overfits_two_pairs(tmp_path):
    """A network whose gradients do not reach its parameters keeps its start's loss.
    Measured at 16², 2 pairs, 150 steps (the rate annealed along a cosine): EK-DUN 0.157 →
    0.0272, Le-ADMM-U 0.214 → 0.0417, UPDN 0.851 → 0.0272 (the scenes' variance 0.051).
    The two networks that end in a U-Net also report what their U-Net was handed (its
    input left 90.5 % and 73.3 % of the scenes' variance unexplained) and how far it gets
    alone from noise, from that input and from the scenes plus noise."""
    spec = VirtualBenchSpec(sensor_shape=(16, 16), n_train=2, n_test=1)
    doc = bc.overfit_check(tmp_path, spec, steps=150, log=lambda text: None)
    for name, result in doc["networks"].items():
        start, end = result["mse"][0][1], result["final_mse"]
        assert end < start / 4 and end < doc["variance"], name
        assert ("denoiser" in result) == (name != "ekdun"), name
    for name in ("le-admm-u", "updn"):
        floor = doc["networks"][name]["denoiser"]
        assert 0 < floor["unexplained"] < 1.2 and floor["noise_floor"] > 0, name
        # the input that holds the scenes: an affine map of it leaves about 1/5 of them
        assert 0.1 < floor["informed_unexplained"] < 0.3, name


def test_a_u_net_handed_the_scenes_fits_them_from_its_own_input_and_not_from_noise():
    """A network whose physics stage hands its (residual, zero-started) U-Net the scenes
    themselves: nothing is left unexplained and the U-Net alone from that input fits them
    exactly, while from noise it must memorise."""
    # not seed 0: the floor's noise is drawn with the seed it is given (0)
    x = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(1))

    class Handed(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.config = SimpleNamespace(denoiser=UNetConfig(widths=(4, 8)))
            self.denoiser = UNet(3, 3, (4, 8))

        def forward(self, y):
            return self.denoiser(x)

    floor = bc.denoiser_floor(Handed(), x, torch.zeros_like(x), steps=30, lr=1e-2)
    assert floor["unexplained"] < 1e-20 and floor["own_floor"] < 1e-12
    assert floor["noise_floor"] > 0.1


def test_the_affine_map_explains_what_the_features_hold():
    """A per-pixel affine map of features that contain the scenes explains them exactly;
    of pure noise it explains (almost) nothing but each colour's mean."""
    generator = torch.Generator().manual_seed(0)
    x = torch.rand(4, 3, 16, 16, generator=generator)
    noise = torch.rand(4, 5, 16, 16, generator=generator)
    assert bc._affine_unexplained(torch.cat([noise, 2 * x - 1], dim=1), x) < 1e-20
    per_colour = float(x.var(dim=(0, 2, 3), unbiased=False).mean())
    assert bc._affine_unexplained(noise, x) == pytest.approx(per_colour, rel=0.01)
    assert bc._affine_unexplained(noise, x) <= per_colour


def test_the_overfit_check_runs_on_the_field_free_bench(tmp_path):
    """``field_free``: the field-free bench's pairs (one PSF everywhere), the network seeded
    with that PSF; the loss falls there too."""
    spec = VirtualBenchSpec(sensor_shape=(16, 16), n_train=2, n_test=1)
    doc = bc.overfit_check(tmp_path, spec, steps=60, networks=["le-admm-u"], field_free=True,
                           log=lambda text: None)
    assert doc["field_free"] and (tmp_path / "field_free" / "centre_psf.npy").is_file()
    assert not (tmp_path / "dataset").exists()          # the varying bench was not made
    result = doc["networks"]["le-admm-u"]
    assert result["final_mse"] < result["mse"][0][1] / 2
    assert "field-free" in (tmp_path / "overfit.md").read_text()
