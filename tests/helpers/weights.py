"""The eigen-kernel weight maps' coordinates on a full grid: the reference the weight tests
evaluate bases on (the product evaluates them separably,
:func:`psfkit.forward.weights.separable_coordinates`)."""

from __future__ import annotations

import numpy as np


def normalized_coordinates(sensor_shape: tuple[int, int],
                           optical_center: tuple[float, float] | None = None,
                           extent: tuple[int, int] | None = None,
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Normalized coordinates ``(u_n, v_n)``, each ``(H, W)``, reaching ±1 at the sensor edges.

    Parameters
    ----------
    sensor_shape : (int, int)
        ``(H', W')`` sensor grid that defines the normalization.
    optical_center : (float, float), optional
        ``(v_c, u_c)`` in sensor pixels; default the sensor centre.
    extent : (int, int), optional
        Evaluate on a larger grid ``(H, W)`` centred on the sensor (e.g. the padded scene
        grid of the forward model); default the sensor grid itself.
    """
    h, w = sensor_shape
    v_c, u_c = optical_center if optical_center is not None else ((h - 1) / 2, (w - 1) / 2)
    eh, ew = extent if extent is not None else (h, w)
    v = np.arange(eh) - (eh - h) // 2
    u = np.arange(ew) - (ew - w) // 2
    u_norm = np.broadcast_to(((u - u_c) / (w / 2))[None, :], (eh, ew))
    v_norm = np.broadcast_to(((v - v_c) / (h / 2))[:, None], (eh, ew))
    return u_norm, v_norm
