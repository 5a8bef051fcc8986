"""The Tukey (tapered-cosine) window, written out: importing ``scipy.signal`` costs about
0.4 s of a command's start-up (a test checks the values equal SciPy's)."""

from __future__ import annotations

import numpy as np


def tukey_window(length: int, alpha: float = 0.5) -> np.ndarray:
    r"""Symmetric Tukey window of ``length`` samples (Harris, Proc. IEEE 66, 51 (1978)).

    Flat (1) in the middle; over the first and last ``alpha·(length − 1)/2`` samples a
    raised cosine :math:`\tfrac12\big(1 + \cos(\pi(2n/(\alpha(N-1)) - 1))\big)` falls to 0 at
    the ends. ``alpha = 0`` is the rectangular window, ``alpha = 1`` the Hann window.

    Returns ``(length,)`` float64, as ``scipy.signal.windows.tukey(length, alpha)``.
    """
    if length <= 1:
        return np.ones(max(length, 0))
    if alpha <= 0:
        return np.ones(length)
    alpha = min(alpha, 1.0)
    n = np.arange(length, dtype=np.float64)
    width = int(np.floor(alpha * (length - 1) / 2.0))
    window = np.ones(length)
    head = n[:width + 1]
    window[:width + 1] = 0.5 * (1 + np.cos(np.pi * (-1 + 2.0 * head / alpha / (length - 1))))
    tail = n[length - width - 1:]
    window[length - width - 1:] = 0.5 * (1 + np.cos(
        np.pi * (-2.0 / alpha + 1 + 2.0 * tail / alpha / (length - 1))))
    return window
