"""End-to-end runs (CLIs in subprocesses, notebooks, analysis scripts): all marked ``e2e``.

The quick loop skips them: ``python -m pytest -m "not e2e"``; CI runs everything.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.e2e)


@pytest.fixture()
def caustic_psf():
    """``(psf, op, rng)``: a caustic-like RGB PSF image ``(24, 32, 3)`` with a 0.02 background,
    its shift-invariant operator (float64) and the generator that drew it, to draw the
    measurements' noise from (classical-reconstruction tests)."""
    import numpy as np
    import torch

    from ekdun.physics.operators import EigenKernelOperator
    from ekdun.reconstruction.classical import psf_model

    rng = np.random.default_rng(4)
    psf = np.full((24, 32, 3), 0.02, np.float32)                       # background level
    psf[rng.integers(4, 20, 40), rng.integers(4, 28, 40)] += rng.random((40, 3)).astype(
        np.float32)
    kernel = psf.transpose(2, 0, 1) - 0.02
    kernel /= kernel.sum(axis=(-2, -1), keepdims=True)
    op = EigenKernelOperator.from_kernel_model(psf_model(kernel, (24, 32), 3),
                                               dtype=torch.float64)
    return psf, op, rng
