"""Kernel-change split (research.compare.kernel_change): synthetic changes of known composition."""

from __future__ import annotations

import numpy as np
import pytest

from psfkit.calibration.registration import shift_image
from psfkit.errors import InvalidInputError
from research.compare.displacement import caustic_support
from research.compare.kernel_change import split_change, split_kernel_changes


def _caustic(shape: tuple[int, int] = (64, 64), seed: int = 3) -> np.ndarray:
    """A caustic-like kernel: a few thin bright curves (Gaussian lines), zero far from them."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    img = np.zeros(shape)
    for _ in range(4):
        cy, cx = rng.uniform(24, 40, 2)
        r = rng.uniform(6, 12)
        dist = np.abs(np.hypot(yy - cy, xx - cx) - r)
        img += np.exp(-0.5 * (dist / 1.2) ** 2) * (np.hypot(yy - cy, xx - cx) < 14)
    img[img < 1e-3] = 0
    return (img / img.sum()).astype(np.float32)


@pytest.fixture(scope="module")
def kernel():
    k = _caustic()
    return k, caustic_support(k[None], dilate=3)


def test_pure_pedestal_is_outside(kernel):
    k, support = kernel
    pedestal = np.where(support, 0, 1.0).astype(np.float32)
    pedestal *= 0.05 / pedestal.sum()            # 5 % extra mass, all outside the caustic
    out = split_change(k + pedestal, k, support)
    assert abs(out["gain"]) < 1e-6 and out["total_gain"] == pytest.approx(0.05, rel=1e-4)
    assert out["fractions"]["pedestal"] > 0.99
    assert out["outside_mass_fraction"] == pytest.approx(0.05 / 1.05, rel=1e-3)


def test_pure_gain(kernel):
    k, support = kernel
    out = split_change(1.2 * k, k, support)
    assert out["gain"] == pytest.approx(0.2, rel=1e-5)
    assert out["fractions"]["gain"] > 0.999
    assert out["pedestal_fraction"] < 1e-6


def test_pure_shift(kernel):
    k, support = kernel
    moved = shift_image(k[None].astype(np.float32), (0.4, -0.3))[0][0]
    out = split_change(moved, k, support)
    assert abs(out["gain"]) < 0.01
    assert out["fractions"]["displacement"] > 0.8, out
    assert out["fractions"]["pedestal"] < 0.02
    assert out["flow_rms_px"] == pytest.approx(0.5, abs=0.1)


def test_mixture_in_proportion(kernel):
    k, support = kernel
    moved = shift_image(k[None].astype(np.float32), (0.4, -0.3))[0][0]
    pedestal = np.where(support, 0, 1.0).astype(np.float32)
    pedestal *= 0.02 / pedestal.sum()
    out = split_change(1.1 * (moved + pedestal), k, support)
    f = out["fractions"]
    assert out["gain"] == pytest.approx(0.1, abs=0.01)
    assert out["total_gain"] == pytest.approx(1.1 * 1.02 - 1, rel=1e-3)
    assert f["gain"] > 0.1 and f["pedestal"] > 0.001 and f["displacement"] > 0.1
    assert sum(f.values()) == pytest.approx(1.0)


def test_sets_and_refusals(kernel):
    k, support = kernel
    learned = np.stack([k, 1.2 * k])[:, None]
    ref = np.stack([k, k])[:, None]
    out = split_kernel_changes(learned, ref, support, ("Kbase", "Kv"))
    assert out["Kbase"]["change_rel"] == 0.0
    assert out["Kv"]["gain"] == pytest.approx(0.2, rel=1e-5)
    assert out["all"]["pedestal_share_of_change"] < 1e-6
    assert out["all"]["outside_mass_fraction"] < 1e-6
    with pytest.raises(InvalidInputError):
        split_change(k, k[:10], support)
