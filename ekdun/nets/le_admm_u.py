r"""Le-ADMM-U (Monakhova et al. 2019): unrolled DiffuserCam ADMM followed by a U-Net.

The ADMM-TV of :mod:`ekdun.nets.tv_admm_steps` with learned ``μ1, μ2, μ3, τ`` per iteration
(log-parametrised), from zero; the central ``H' × W'`` of ``x`` is refined by the U-Net. Unlike
the reference code: no per-image max normalisation before the U-Net, the shared U-Net block.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

from torch import Tensor

from ekdun.nets.configs import LeADMMUConfig
from ekdun.nets.tv_admm_steps import (
    admm_tv_context,
    admm_tv_initial_state,
    admm_tv_iteration,
    finite_difference_spectrum,
)
from ekdun.nets.unet import UNet
from ekdun.nets.unrolled import State, UnrolledNetwork
from ekdun.physics.operators import ShiftInvariantOperator
from psfkit.forward.convolution import crop


class LeADMMU(UnrolledNetwork):
    """Le-ADMM-U baseline.

    Parameters
    ----------
    physics : ShiftInvariantOperator
        The measured PSF (fixed: ``trainable=False``).
    config : LeADMMUConfig
    """

    def __init__(self, physics: ShiftInvariantOperator,
                 config: LeADMMUConfig | None = None) -> None:
        config = config or LeADMMUConfig()
        super().__init__(physics, config)
        lipschitz = max(physics.lipschitz_bound(), 1e-12)
        dtype = physics.kernels.dtype
        mu2 = config.mu2_scale * lipschitz
        self.log_mu1 = self.per_iteration(math.log(config.mu1_init), dtype)
        self.log_mu2 = self.per_iteration(math.log(mu2), dtype)
        self.log_mu3 = self.per_iteration(math.log(config.mu3_scale * lipschitz), dtype)
        self.log_tau = self.per_iteration(math.log(config.tau_scale * mu2), dtype)
        self.register_buffer("tv_spectrum",
                             finite_difference_spectrum(physics.grid_shape, dtype),
                             persistent=False)
        channels = physics.channels
        self.denoiser = UNet(channels, channels, **asdict(config.denoiser))

    def prepare(self, y: Tensor) -> dict[str, Any]:
        op = self.physics.prepare()
        op.check(y, "measurement")
        # conj_spectra are cached (fixed PSF)
        return admm_tv_context(y, op.spectra[0], op.conj_spectra[0], self.physics.grid_shape)

    def initial_state(self, y: Tensor, context: dict[str, Any]) -> State:
        return admm_tv_initial_state(context)

    def update(self, i: int, state: State, context: dict[str, Any]) -> State:
        return admm_tv_iteration(state, context, self.log_mu1[i].exp(), self.log_mu2[i].exp(),
                                 self.log_mu3[i].exp(), self.log_tau[i].exp(),
                                 self.tv_spectrum)

    def output(self, state: State, context: dict[str, Any]) -> Tensor:
        return self.denoiser(crop(state["x"], self.physics.sensor_shape))
