"""A synthetic diffuser-like PSF for tests and benchmarks (no data needed).

Was ``ekdun.physics.synthetic`` until issue 44: no product code calls it. The benchmarks in
``benchmarks/`` put the checkout's root on ``sys.path`` to import it.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def caustic_psf(sensor_shape: tuple[int, int], channels: int = 3, seed: int = 0,
                spots: int = 400, blur: float = 1.0) -> np.ndarray:
    """A caustic-like PSF ``(C, H', W')`` float32, each channel summing to 1.

    Bright sharp spots scattered over a disc (the diffuser's footprint on the sensor, centred
    at ``(H'//2, W'//2)``, the kernel origin), blurred by a Gaussian of ``blur`` pixels, with a
    slightly different spot brightness per channel (dispersion). Not a physical simulation;
    see :mod:`psfkit.simulate` for one.
    """
    h, w = sensor_shape
    rng = np.random.default_rng(seed)
    radius = 0.4 * min(h, w)
    angle = rng.uniform(0, 2 * np.pi, spots)
    dist = radius * np.sqrt(rng.uniform(0, 1, spots))
    rows = np.clip(np.round(h // 2 + dist * np.sin(angle)).astype(int), 0, h - 1)
    cols = np.clip(np.round(w // 2 + dist * np.cos(angle)).astype(int), 0, w - 1)
    psf = np.zeros((channels, h, w), np.float64)
    for c in range(channels):
        np.add.at(psf[c], (rows, cols), rng.uniform(0.5, 1.5, spots))
        psf[c] = ndimage.gaussian_filter(psf[c], blur, mode="constant")
        psf[c] /= psf[c].sum()
    return psf.astype(np.float32)
