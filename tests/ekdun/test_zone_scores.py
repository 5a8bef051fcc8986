"""PSNR and SSIM by field zone (``ekdun eval``'s ``by_zone``) against direct computations, on
the zones that psfkit's eval-model uses."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from ekdun.evaluation.evaluate import ZoneScores, recorded_optical_center
from ekdun.evaluation.metrics import SSIM_MARGIN, psnr
from psfkit.forward.kernelfile import KernelModel
from psfkit.forward.zones import ZONE_NAMES, field_zones


@pytest.mark.parametrize("centre", [None, (12.0, 30.0)])
def test_zone_psnr_and_ssim_match_direct_computations(centre):
    rng = np.random.default_rng(1)
    shape = (40, 52)
    truth = rng.random((3, 3, *shape))
    recon = np.clip(truth + 0.05 * rng.standard_normal(truth.shape), 0, 1)
    zones = field_zones(shape, centre)
    # the error grows towards the edge zone: its PSNR must come out lowest
    recon[..., zones.labels == 2] = np.clip(truth[..., zones.labels == 2] + 0.2, 0, 1)
    scores = ZoneScores(shape, centre)
    assert np.array_equal(scores.zones.labels, zones.labels)     # psfkit's one definition
    for i in range(3):
        scores.add(torch.as_tensor(recon[i:i + 1]), torch.as_tensor(truth[i:i + 1]))
    summary = scores.summary()
    m = SSIM_MARGIN
    inner = zones.cropped(m).masks()
    for i in range(3):
        _, local = structural_similarity(np.moveaxis(truth[i], 0, -1),
                                         np.moveaxis(recon[i], 0, -1), data_range=1.0,
                                         channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, full=True)
        local = local[m:-m, m:-m]
        for zone, mask in zones.masks().items():
            mse = np.mean((truth[i] - recon[i])[:, mask] ** 2)
            assert summary[zone]["psnr_per_pair"][i] == pytest.approx(10 * np.log10(1 / mse),
                                                                      abs=1e-9)
            assert summary[zone]["ssim_per_pair"][i] == pytest.approx(
                local[inner[zone]].mean(), abs=1e-6)
    assert summary["edge"]["psnr"] < summary["middle"]["psnr"] - 5
    assert set(summary) == set(ZONE_NAMES)


def test_masked_psnr_of_the_whole_sensor_is_the_psnr():
    rng = np.random.default_rng(2)
    x = torch.rand(2, 3, 9, 11, generator=torch.Generator().manual_seed(0))
    y = x + 0.01 * torch.as_tensor(rng.standard_normal(x.shape))
    everything = torch.ones(9, 11, dtype=torch.bool)
    assert torch.allclose(psnr(y, x, mask=everything), psnr(y, x))


def test_zones_of_a_checkpoint_follow_its_kernel_files_optical_centre():
    model = KernelModel(kernels=np.ones((1, 1, 8, 10), np.float32), basis="si",
                        sensor_shape=(8, 10), channels=("L",), optical_center=(2.0, 3.5))
    assert recorded_optical_center({"kernel_metadata": model.to_metadata()}) == (2.0, 3.5)
    assert recorded_optical_center({}) is None
