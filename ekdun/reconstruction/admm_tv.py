r"""Classical ADMM with total-variation regularisation for a shift-invariant PSF.

For users without a trained network (the DiffuserCam tutorial's algorithm, Antipa et al.
2018): solve

.. math::

    \min_{v \ge 0}\ \tfrac12 \lVert y - C(h * v)\rVert^2 + \tau \lVert \nabla v \rVert_1

with ``v`` on the padded grid (``scene_padding × H'``), ``C`` the crop to the sensor and
``h * ·`` a circular FFT convolution (exactly ``y = crop(K * pad(x))`` of ``design.md`` for a
scene inside the central block). Every update is closed-form; they are the steps of
:mod:`ekdun.models.tv_admm_steps`, shared with Le-ADMM-U (which learns ``μ`` and ``τ``
per iteration), and every FFT goes through :mod:`psfkit.forward`.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ekdun.errors import TensorShapeError
from ekdun.models.tv_admm_steps import (
    admm_tv_context,
    admm_tv_initial_state,
    admm_tv_iteration,
    finite_difference_spectrum,
)
from psfkit.forward.convolution import crop, kernel_spectra
from psfkit.forward.geometry import padded_shape


def admm_tv(measurement: np.ndarray | Tensor, psf: np.ndarray | Tensor, iterations: int = 100,
            tau: float = 1e-3, mu1: float = 0.1, mu2: float = 0.01, mu3: float = 0.1,
            scene_padding: int = 2, normalize_psf: bool = True,
            full_grid: bool = False, dtype: torch.dtype = torch.float64) -> Tensor:
    """Reconstruct a scene from one measurement with ADMM-TV.

    Parameters
    ----------
    measurement : array ``(C, H', W')`` or ``(H', W')``
        Background-subtracted measurement.
    psf : array ``(C, Hk, Wk)`` or ``(Hk, Wk)``
        Measured PSF (origin at its centre), ``Hk <= H'``, ``Wk <= W'``; mono PSFs are used
        for every channel.
    iterations : int
        ADMM iterations.
    tau : float
        TV weight relative to the peak of the measurement (scale-free).
    mu1, mu2, mu3 : float
        Penalties of the data, TV and non-negativity splits, relative to ``max |ĥ|²``
        (``mu2`` relative to 1).
    scene_padding : int
        Padded-grid factor (2: the scene may be as large as the sensor).
    normalize_psf : bool
        Scale each PSF channel to unit sum first (reconstruction in measurement units).
    full_grid : bool
        Return the whole padded grid instead of its central ``H' × W'`` block.
    dtype : torch.dtype
        Working precision (float64 by default; float32 is about twice as fast).

    Returns
    -------
    Tensor
        ``(C, H', W')`` in ``dtype`` (or the padded grid).
    """
    y = torch.as_tensor(np.asarray(measurement), dtype=dtype)
    h = torch.as_tensor(np.asarray(psf), dtype=dtype)
    if y.ndim == 2:
        y = y[None]
    if h.ndim == 2:
        h = h[None]
    if y.ndim != 3 or h.ndim != 3:
        raise TensorShapeError("measurement and PSF must be (C, H, W) or (H, W)")
    if h.shape[0] == 1 and y.shape[0] > 1:
        h = h.expand(y.shape[0], -1, -1)
    if h.shape[0] != y.shape[0]:
        raise TensorShapeError(f"PSF has {h.shape[0]} channels, measurement {y.shape[0]}")
    sensor = (int(y.shape[-2]), int(y.shape[-1]))
    if h.shape[-2] > sensor[0] or h.shape[-1] > sensor[1]:
        raise TensorShapeError(f"PSF {h.shape[-2]}x{h.shape[-1]} is larger than the "
                               f"measurement {sensor[0]}x{sensor[1]}")
    if normalize_psf:
        h = h / h.sum(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
    grid = padded_shape(sensor, scene_padding)
    scale = float(y.abs().max().clamp_min(1e-12))
    y = y / scale
    H = kernel_spectra(h, grid)                         # (C, PH, PW//2+1)
    lipschitz = float((H.abs() ** 2).max())
    context = admm_tv_context(y, H, H.conj().resolve_conj(), grid)
    tv_spectrum = finite_difference_spectrum(grid, dtype)
    mu1, mu3 = mu1 * lipschitz, mu3 * lipschitz
    state = admm_tv_initial_state(context)
    for _ in range(iterations):
        state = admm_tv_iteration(state, context, mu1, mu2, mu3, tau, tv_spectrum)
    v = state["x"]
    out = v.clamp_min(0) * scale
    return out if full_grid else crop(out, sensor).contiguous()
