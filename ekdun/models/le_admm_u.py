r"""Le-ADMM-U (Monakhova et al. 2019): unrolled DiffuserCam ADMM followed by a U-Net.

The ADMM of DiffuserCam (Antipa et al. 2018) solves

.. math::

    \min_{x \ge 0}\ \tfrac12 \| y - C H x \|_2^2 + \tau \|\Psi x\|_1

for ``x`` on the padded grid ``(P·H', P·W')`` (``H`` the circular convolution with the fixed
measured PSF there, ``C`` the crop to the sensor, ``Ψ`` circular forward differences) with the
splits ``v = Hx`` (crop), ``u = Ψx`` (TV) and ``w = x`` (non-negativity). Iteration ``i`` with
learned ``μ1, μ2, μ3, τ`` (kept positive by a log parametrisation):

.. math::

    u &\leftarrow \mathcal{S}_{\tau/\mu_2}(\Psi x + \alpha_2/\mu_2) \\
    v &\leftarrow (C^\top C + \mu_1)^{-1}(\alpha_1 + \mu_1 H x + C^\top y) \\
    w &\leftarrow \max(x + \alpha_3/\mu_3, 0) \\
    x &\leftarrow (\mu_1 H^\top H + \mu_2 \Psi^\top\Psi + \mu_3)^{-1}
          \big[(\mu_3 w - \alpha_3) + \Psi^\top(\mu_2 u - \alpha_2)
                + H^\top(\mu_1 v - \alpha_1)\big] \\
    \alpha_1 &\mathrel{+}= \mu_1 (Hx - v), \quad
    \alpha_2 \mathrel{+}= \mu_2 (\Psi x - u), \quad
    \alpha_3 \mathrel{+}= \mu_3 (x - w)

The ``x`` update is exact in the Fourier domain (``HᵀH`` and ``ΨᵀΨ`` are both diagonalised by
the padded-grid FFT). ``𝒮`` is the anisotropic soft threshold. All variables start at zero.
Each iteration takes two forward and two inverse FFTs. The estimate is the central
``H' × W'`` of ``x`` (our scenes have the sensor's size), which the U-Net then refines.
Differences from the reference code: no per-image max normalisation before the U-Net, and
the shared U-Net block (see :mod:`ekdun.models.configs`).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

from ekdun.models.configs import LeADMMUConfig
from ekdun.models.unet import UNet
from ekdun.models.unrolled import State, UnrolledNetwork
from ekdun.physics.operators import ShiftInvariantOperator
from psfkit.forward.convolution import crop, pad
from psfkit.forward.fft import irfft2, rfft2


def finite_differences(x: Tensor) -> Tensor:
    """``Ψx``: circular forward differences along rows and columns, ``(2, *x.shape)``."""
    return torch.stack([torch.roll(x, -1, dims=-2) - x, torch.roll(x, -1, dims=-1) - x])


def finite_differences_adjoint(u: Tensor) -> Tensor:
    """``Ψᵀu`` for ``u`` ``(2, ...)``: the exact adjoint of :func:`finite_differences`."""
    return (torch.roll(u[0], 1, dims=-2) - u[0]) + (torch.roll(u[1], 1, dims=-1) - u[1])


def finite_difference_spectrum(grid_shape: tuple[int, int], dtype: torch.dtype) -> Tensor:
    """Eigenvalues of ``ΨᵀΨ`` on the ``rfft2`` grid, ``(PH, PW//2 + 1)``."""
    rows = 2.0 * torch.pi * torch.arange(grid_shape[0], dtype=torch.float64) / grid_shape[0]
    cols = (2.0 * torch.pi * torch.arange(grid_shape[1] // 2 + 1, dtype=torch.float64)
            / grid_shape[1])
    return ((2 - 2 * torch.cos(rows))[:, None] + (2 - 2 * torch.cos(cols))[None, :]).to(dtype)


class LeADMMU(UnrolledNetwork):
    """Le-ADMM-U baseline.

    Parameters
    ----------
    physics : ShiftInvariantOperator
        The measured PSF (kept fixed: build it with ``trainable=False``).
    config : LeADMMUConfig
        Iterations (5), U-Net and initial values.
    """

    def __init__(self, physics: ShiftInvariantOperator,
                 config: LeADMMUConfig | None = None) -> None:
        config = config or LeADMMUConfig()
        super().__init__(config.iterations)
        self.config = config
        self.physics = physics
        lipschitz = max(physics.lipschitz_bound(), 1e-12)
        dtype = physics.kernels.dtype
        n = config.iterations
        mu2 = config.mu2_scale * lipschitz

        def log_param(value: float) -> nn.Parameter:
            return nn.Parameter(torch.full((n,), math.log(value), dtype=dtype))

        self.log_mu1 = log_param(config.mu1_init)
        self.log_mu2 = log_param(mu2)
        self.log_mu3 = log_param(config.mu3_scale * lipschitz)
        self.log_tau = log_param(config.tau_scale * mu2)
        self.register_buffer("tv_spectrum",
                             finite_difference_spectrum(physics.grid_shape, dtype),
                             persistent=False)
        channels = physics.channels
        self.denoiser = UNet(channels, channels, config.denoiser.widths,
                             config.denoiser.residual, config.denoiser.zero_init_output)

    def prepare(self, y: Tensor) -> dict[str, Any]:
        op = self.physics.prepare()
        op.check(y, "measurement")
        spectrum = op.spectra[0]                                   # (C, PH, PW//2+1)
        grid = self.physics.grid_shape
        return {
            "spectrum": spectrum,
            "conj_spectrum": op.conj_spectra[0],                   # cached (fixed PSF)
            "hth": spectrum.real ** 2 + spectrum.imag ** 2,
            "cty": pad(y, grid),                                # Cᵀy
            "ctc": pad(torch.ones_like(y[:1, :1]), grid),       # CᵀC, a 0/1 mask
        }

    def initial_state(self, y: Tensor, context: dict[str, Any]) -> State:
        zeros = torch.zeros_like(context["cty"])
        return {"x": zeros, "hx": zeros, "alpha1": zeros,
                "alpha2": torch.zeros((2, *zeros.shape), dtype=zeros.dtype,
                                      device=zeros.device),
                "alpha3": zeros}

    def update(self, i: int, state: State, context: dict[str, Any]) -> State:
        mu1, mu2 = self.log_mu1[i].exp(), self.log_mu2[i].exp()
        mu3, tau = self.log_mu3[i].exp(), self.log_tau[i].exp()
        x, hx = state["x"], state["hx"]
        alpha1, alpha2, alpha3 = state["alpha1"], state["alpha2"], state["alpha3"]
        grid = self.physics.grid_shape
        spectrum = context["spectrum"]

        psi_x = finite_differences(x)
        shifted = psi_x + alpha2 / mu2
        u = torch.sign(shifted) * torch.relu(shifted.abs() - tau / mu2)
        v = (alpha1 + mu1 * hx + context["cty"]) / (context["ctc"] + mu1)
        w = torch.relu(x + alpha3 / mu3)

        rhs = (mu3 * w - alpha3) + finite_differences_adjoint(mu2 * u - alpha2)
        numerator = rfft2(rhs) + context["conj_spectrum"] * rfft2(mu1 * v - alpha1)
        x_hat = numerator / (mu1 * context["hth"] + mu2 * self.tv_spectrum + mu3)
        x = irfft2(x_hat, grid)
        hx = irfft2(spectrum * x_hat, grid)

        return {"x": x, "hx": hx,
                "alpha1": alpha1 + mu1 * (hx - v),
                "alpha2": alpha2 + mu2 * (finite_differences(x) - u),
                "alpha3": alpha3 + mu3 * (x - w)}

    def admm_estimate(self, y: Tensor) -> Tensor:
        """The cropped ADMM iterate before the U-Net, ``(B, C, H', W')``."""
        state, _ = self.iterate(y)
        return crop(state["x"], self.physics.sensor_shape)

    def output(self, state: State, context: dict[str, Any]) -> Tensor:
        return self.denoiser(crop(state["x"], self.physics.sensor_shape))
