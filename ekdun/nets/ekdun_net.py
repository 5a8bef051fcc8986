r"""EK-DUN: the ADMM deep unrolled network with the eigen-kernel forward model (Secs. 3.2, 4.3).

Iteration ``i`` (Eqs. 4–6, the second rearranged to need one ``A`` and one ``Aᵀ``), with ``A``
the forward model the schedule picks for it and ``𝑃⁽ⁱ⁾`` a U-Net per iteration:

.. math::

    g^{(i+1)} &= \mathbb{P}^{(i)}(f^{(i)} - d^{(i)}) \\
    f^{(i+1)} &= f^{(i)} - \epsilon^{(i)} A^\top(A f^{(i)} - y)
                 - \epsilon^{(i)}\eta^{(i)}\,(f^{(i)} - g^{(i+1)} - d^{(i)}) \\
    d^{(i+1)} &= d^{(i)} + \kappa^{(i)} (g^{(i+1)} - f^{(i+1)})

from ``f⁰ = Aᵀy``, ``d⁰ = 0``; the output is ``f^I``. Models: base
``y = crop(K_base * pad(x))`` or eigen-kernel (Eq. 7); schedules (Table 2): ``"base"``,
``"last-k"`` (eigen model in the last ``k`` iterations) and ``"all"`` (also for ``f⁰``).
With a kernel module (:meth:`EKDUN.use_kernel_module`, e.g. research/kernel_models.py),
``physics.kernels`` is a fixed copy refreshed in eval mode and on loading a state dict.
``ε = exp(·)``, ``η = exp(·)`` start at ``step_scale / L`` and ``penalty_scale · L``
(``L = max |K̂|²``); with zero-initialised residual U-Nets the initial network is ``I``
gradient steps of size ``1/L`` on ``½‖Af − y‖²``: stable.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

import torch
from torch import Tensor, nn

from ekdun.nets.configs import EKDUNConfig, parse_schedule
from ekdun.nets.unet import UNet
from ekdun.nets.unrolled import State, UnrolledNetwork
from ekdun.physics.operators import EigenKernelOperator, PreparedOperator
from psfkit.forward.convolution import kernel_spectra


class EKDUN(UnrolledNetwork):
    """Eigen-Kernel Deep Unrolled Network.

    Parameters
    ----------
    physics : EigenKernelOperator
        The eigen-kernel model (first kernel: the base); learned when ``trainable=True``.
    config : EKDUNConfig
    """

    def __init__(self, physics: EigenKernelOperator, config: EKDUNConfig | None = None) -> None:
        config = config or EKDUNConfig()
        super().__init__(physics, config)
        self.eigen_initial, self.eigen_schedule = parse_schedule(
            config.schedule, config.iterations, config.eigen_last)
        channels = physics.channels
        self.priors = nn.ModuleList(
            UNet(channels, channels, **asdict(config.prior)) for _ in range(config.iterations))
        lipschitz = max(physics.lipschitz_bound(), 1e-12)
        dtype = physics.kernels.dtype
        self.log_eps = self.per_iteration(math.log(config.step_scale / lipschitz), dtype)
        self.log_eta = self.per_iteration(math.log(config.penalty_scale * lipschitz), dtype)
        self.kappa = self.per_iteration(config.kappa_init, dtype)
        self.kernel_param: nn.Module | None = None

    def use_kernel_module(self, module: nn.Module) -> None:
        """Make the kernels with ``module`` (``module() -> (K, C, Hk, Wk)``, trained under the
        ``kernel_param.`` prefix) instead of free pixels; ``physics.kernels`` becomes its copy."""
        self.kernel_param = module
        self.physics.kernels.requires_grad_(False)
        self.sync_kernels()
        self.register_load_state_dict_post_hook(lambda module, _keys: module.sync_kernels())

    def current_kernels(self) -> Tensor:
        """The kernels ``(K, C, Hk, Wk)`` the network uses now (differentiable)."""
        return self.physics.kernels if self.kernel_param is None else self.kernel_param()

    def sync_kernels(self) -> None:
        """Copy the parameterised kernels into ``physics`` (and refresh its spectra)."""
        if self.kernel_param is None:
            return
        with torch.no_grad():
            self.physics.kernels.copy_(self.kernel_param())
        self.physics.refresh_spectra()

    def train(self, mode: bool = True) -> EKDUN:
        super().train(mode)
        if not mode:
            self.sync_kernels()
        return self

    def _spectra(self, first: int | None = None) -> Tensor:
        if self.kernel_param is None or not self.training:
            return self.physics.spectra(first)
        kernels = self.kernel_param()
        return kernel_spectra(kernels if first is None else kernels[:first],
                              self.physics.grid_shape)

    @property
    def uses_eigen_kernels(self) -> bool:
        """Whether any step (``f⁰`` or an iteration) uses the eigen-kernel model."""
        return self.eigen_initial or any(self.eigen_schedule)

    def forward_model(self) -> PreparedOperator:
        """``A_θ`` with the current kernels: the eigen-kernel model, or ``Kbase`` alone when no
        step uses it."""
        if self.uses_eigen_kernels:
            return self.physics.prepare(self._spectra())
        return self.physics.prepare_base(self._spectra(first=1))

    def prepare(self, y: Tensor) -> dict[str, Any]:
        # One kernel FFT batch per forward pass, reused by every iteration; the base model
        # shares the eigen-kernel model's spectra (and their conjugates).
        if self.uses_eigen_kernels:
            eigen = self.physics.prepare(self._spectra())
            base = self.physics.prepare_base(eigen.spectra, eigen.conj_spectra)
        else:
            eigen = None
            base = self.physics.prepare_base(self._spectra(first=1))
        base.check(y, "measurement")
        return {"y": y, "base": base, "eigen": eigen}

    def initial_state(self, y: Tensor, context: dict[str, Any]) -> State:
        op = context["eigen"] if self.eigen_initial else context["base"]
        f = op.A_adjoint(y)
        return {"f": f, "d": torch.zeros_like(f)}

    def update(self, i: int, state: State, context: dict[str, Any]) -> State:
        op = context["eigen"] if self.eigen_schedule[i] else context["base"]
        f, d = state["f"], state["d"]
        eps, eta = self.log_eps[i].exp(), self.log_eta[i].exp()
        g = self.priors[i](f - d)
        gradient = op.A_adjoint(op.A(f) - context["y"])
        f_next = f - eps * gradient - (eps * eta) * (f - g - d)
        d_next = d + self.kappa[i] * (g - f_next)
        return {"f": f_next, "d": d_next}

    def output(self, state: State, context: dict[str, Any]) -> Tensor:
        return state["f"]
