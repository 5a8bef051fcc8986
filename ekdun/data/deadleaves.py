"""Dead-leaves scenes (Matheron; Lee, Mumford & Huang 2001): opaque disks of random colour
with radii ``p(r) ∝ r⁻³``, scale invariant with sharp occlusion edges, a standard test prior.
"""

from __future__ import annotations

import numpy as np

from ekdun.errors import ConfigurationError


def sample_radii(rng: np.random.Generator, n: int, r_min: float, r_max: float) -> np.ndarray:
    """``n`` radii from ``p(r) ∝ r⁻³`` on ``[r_min, r_max]`` (inverse-CDF sampling)."""
    u = rng.random(n)
    a, b = r_min ** -2, r_max ** -2
    return (a - u * (a - b)) ** -0.5


def dead_leaves(shape: tuple[int, int], rng: np.random.Generator | int = 0, *,
                channels: int = 3, r_min: float = 1.0, r_max: float | None = None,
                max_disks: int = 20_000, coverage: float = 0.999) -> np.ndarray:
    """One dead-leaves image.

    Disks are laid front to back (so generation stops once ``coverage`` is reached), in
    colours mixing a common grey level with per-channel noise.

    Parameters
    ----------
    shape : (int, int)
        ``(H, W)``.
    rng : numpy.random.Generator or int
    channels : int
        1 (grey) or 3 (RGB).
    r_min, r_max : float
        Disk radii range in pixels (``r_max`` defaults to half the longest side).
    max_disks : int
    coverage : float
        Stop once this fraction of pixels is covered.

    Returns
    -------
    numpy.ndarray
        ``(C, H, W)`` float32 in ``[0, 1]``.
    """
    if channels not in (1, 3):
        raise ConfigurationError(f"channels must be 1 or 3, got {channels}")
    h, w = int(shape[0]), int(shape[1])
    if h < 1 or w < 1:
        raise ConfigurationError(f"image shape must be positive, got {shape}")
    rng = np.random.default_rng(rng)
    r_max = float(r_max if r_max is not None else max(h, w) / 2)
    if not 0 < r_min < r_max:
        raise ConfigurationError(f"need 0 < r_min < r_max, got {r_min}, {r_max}")
    image = np.zeros((channels, h, w), dtype=np.float32)
    covered = np.zeros((h, w), dtype=bool)
    target = coverage * h * w
    n_covered = 0
    batch = 256
    drawn = 0
    while drawn < max_disks and n_covered < target:
        radii = sample_radii(rng, batch, r_min, r_max)
        centres = rng.random((batch, 2)) * [h + 2 * r_max, w + 2 * r_max] - r_max
        grey = rng.random(batch)
        colours = 0.5 * grey[:, None] + 0.5 * rng.random((batch, channels))
        for k in range(batch):
            r = radii[k]
            cy, cx = centres[k]
            y0, y1 = max(int(np.floor(cy - r)), 0), min(int(np.ceil(cy + r)) + 1, h)
            x0, x1 = max(int(np.floor(cx - r)), 0), min(int(np.ceil(cx + r)) + 1, w)
            if y0 >= y1 or x0 >= x1:
                continue
            yy = np.arange(y0, y1)[:, None] - cy
            xx = np.arange(x0, x1)[None, :] - cx
            new = (yy * yy + xx * xx <= r * r) & ~covered[y0:y1, x0:x1]
            count = int(new.sum())
            if count:
                covered[y0:y1, x0:x1] |= new
                image[:, y0:y1, x0:x1][:, new] = colours[k][:, None]
                n_covered += count
        drawn += batch
    return image
