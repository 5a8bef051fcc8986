r"""Classical ADMM with total-variation regularisation for a shift-invariant PSF.

For users without a trained network (the DiffuserCam tutorial's algorithm, Antipa et al.
2018): solve

.. math::

    \min_{v \ge 0}\ \tfrac12 \lVert y - C(h * v)\rVert^2 + \tau \lVert \nabla v \rVert_1

with ``v`` on the padded grid (``scene_padding × H'``), ``C`` the crop to the sensor and
``h * ·`` a circular FFT convolution (exactly ``y = crop(K * pad(x))`` of ``design.md`` for a
scene inside the central block). Splitting ``x = h * v`` (data), ``u = ∇v`` (TV) and
``w = v`` (non-negativity) makes every update closed-form: the ``x`` update is a per-pixel
division, ``u`` a soft threshold, ``w`` a clip, and ``v`` one division in Fourier space.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ekdun.errors import TensorShapeError
from psfkit.forward.convolution import crop, kernel_spectra, pad
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.geometry import padded_shape


def _grad(v: Tensor) -> tuple[Tensor, Tensor]:
    return torch.roll(v, -1, -2) - v, torch.roll(v, -1, -1) - v


def _grad_adjoint(gy: Tensor, gx: Tensor) -> Tensor:
    return (torch.roll(gy, 1, -2) - gy) + (torch.roll(gx, 1, -1) - gx)


def admm_tv(measurement: np.ndarray | Tensor, psf: np.ndarray | Tensor, iterations: int = 100,
            tau: float = 1e-3, mu1: float = 0.1, mu2: float = 0.01, mu3: float = 0.1,
            scene_padding: int = 2, normalize_psf: bool = True,
            full_grid: bool = False) -> Tensor:
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

    Returns
    -------
    Tensor
        ``(C, H', W')`` float64 (or the padded grid).
    """
    y = torch.as_tensor(np.asarray(measurement), dtype=torch.float64)
    h = torch.as_tensor(np.asarray(psf), dtype=torch.float64)
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
    HtH = (H.abs() ** 2)
    lipschitz = float(HtH.max())
    mu1, mu2, mu3 = mu1 * lipschitz, mu2, mu3 * lipschitz
    ky = torch.fft.fftfreq(grid[0], dtype=torch.float64)[:, None]
    kx = torch.fft.rfftfreq(grid[1], dtype=torch.float64)[None, :]
    lap = (2 - 2 * torch.cos(2 * np.pi * ky)) + (2 - 2 * torch.cos(2 * np.pi * kx))
    denom = mu1 * HtH + mu2 * lap + mu3

    def conv(v: Tensor) -> Tensor:
        return irfft2(rfft2(v) * H, grid)

    def conv_t(v: Tensor) -> Tensor:
        return irfft2(rfft2(v) * H.conj(), grid)

    cty = pad(y, grid)
    mask = pad(torch.ones_like(y), grid)
    v = torch.zeros((y.shape[0], *grid), dtype=torch.float64)
    xi = torch.zeros_like(v)
    rho = torch.zeros_like(v)
    eta_y, eta_x = torch.zeros_like(v), torch.zeros_like(v)
    hv = conv(v)
    gy, gx = _grad(v)
    for _ in range(iterations):
        uy = torch.sign(gy + eta_y / mu2) * (torch.abs(gy + eta_y / mu2) - tau / mu2).clamp_min(0)
        ux = torch.sign(gx + eta_x / mu2) * (torch.abs(gx + eta_x / mu2) - tau / mu2).clamp_min(0)
        x = (cty + mu1 * hv + xi) / (mask + mu1)
        w = (v + rho / mu3).clamp_min(0)
        rhs = (mu3 * w - rho) + _grad_adjoint(mu2 * uy - eta_y, mu2 * ux - eta_x) \
            + conv_t(mu1 * x - xi)
        v = irfft2(rfft2(rhs) / denom, grid)
        hv = conv(v)
        gy, gx = _grad(v)
        xi = xi + mu1 * (hv - x)
        eta_y = eta_y + mu2 * (gy - uy)
        eta_x = eta_x + mu2 * (gx - ux)
        rho = rho + mu3 * (v - w)
    out = v.clamp_min(0) * scale
    return out if full_grid else crop(out, sensor).contiguous()
