r"""EK-DUN: the ADMM deep unrolled network with the eigen-kernel forward model (Secs. 3.2, 4.3).

Iteration ``i`` (Eqs. 4–6), with ``A`` the forward model the schedule picks for it:

.. math::

    g^{(i+1)} &= \mathbb{P}^{(i)}(f^{(i)} - d^{(i)}) \\
    f^{(i+1)} &= f^{(i)} - \epsilon^{(i)} A^\top(A f^{(i)} - y)
                 - \epsilon^{(i)}\eta^{(i)}\,(f^{(i)} - g^{(i+1)} - d^{(i)}) \\
    d^{(i+1)} &= d^{(i)} + \kappa^{(i)} (g^{(i+1)} - f^{(i+1)})

(the second line is Eq. 5 rearranged so that one ``A`` and one ``Aᵀ`` suffice), starting from
``f⁰ = Aᵀy``, ``d⁰ = 0``; the output is ``f^I``. ``𝑃⁽ⁱ⁾`` is a U-Net per iteration.

Forward models (shared kernels ``K_base, K_v, K_h``, trainable):

* base: ``y = crop(K_base * pad(x))`` (shift-invariant, weight 1);
* eigen-kernel: Eq. 7 (sensor side, or whatever the kernel file says).

Schedules (Table 2): ``"base"`` uses the base model everywhere; ``"last-k"`` the eigen-kernel
model in the last ``k`` iterations (base model for ``f⁰``); ``"all"`` the eigen-kernel model
everywhere including ``f⁰``. Kernel spectra are taken once per forward pass (only the base
kernel's for ``"base"``).

Kernels: free pixels in ``physics`` (``kernel_param="free"``), or made by a
:mod:`~ekdun.physics.kernel_parameterisation` module (``self.kernel_param``) in training mode;
``physics.kernels`` is then a fixed copy, brought up to date (with cached spectra) whenever
the network is put in eval mode or loads a state dict.

Parameters ``ε⁽ⁱ⁾ = exp(·)`` and ``η⁽ⁱ⁾ = exp(·)`` are kept positive by a log parametrisation;
``κ⁽ⁱ⁾`` is free. Initial values: ``ε = step_scale / L``, ``η = penalty_scale · L`` with
``L = max |K̂|² ≈ ‖AᵀA‖`` and ``κ = kappa_init``. With the default zero-initialised residual
U-Nets the prior starts as the identity, ``g + d = f``, and the initial network is exactly
``I`` steps of gradient descent on ``½‖Af − y‖²`` with step ``1/L``: stable.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

from ekdun.nets.configs import EKDUNConfig, parse_schedule
from ekdun.nets.unet import UNet
from ekdun.nets.unrolled import State, UnrolledNetwork
from ekdun.physics.kernel_parameterisation import build_parameterisation
from ekdun.physics.operators import EigenKernelOperator, PreparedOperator
from psfkit.forward.convolution import kernel_spectra


class EKDUN(UnrolledNetwork):
    """Eigen-Kernel Deep Unrolled Network.

    Parameters
    ----------
    physics : EigenKernelOperator
        The eigen-kernel model; its first kernel is the base kernel. Its kernels are learned
        with the network when they are an ``nn.Parameter`` (``trainable=True``).
    config : EKDUNConfig
        Iterations, schedule, prior U-Net and initial values.
    """

    def __init__(self, physics: EigenKernelOperator, config: EKDUNConfig | None = None) -> None:
        config = config or EKDUNConfig()
        super().__init__(config.iterations)
        self.config = config
        self.physics = physics
        self.eigen_initial, self.eigen_schedule = parse_schedule(
            config.schedule, config.iterations, config.eigen_last)
        channels = physics.channels
        self.priors = nn.ModuleList(
            UNet(channels, channels, config.prior.widths, config.prior.residual,
                 config.prior.zero_init_output) for _ in range(config.iterations))
        lipschitz = max(physics.lipschitz_bound(), 1e-12)
        dtype = physics.kernels.dtype
        self.log_eps = nn.Parameter(torch.full(
            (config.iterations,), math.log(config.step_scale / lipschitz), dtype=dtype))
        self.log_eta = nn.Parameter(torch.full(
            (config.iterations,), math.log(config.penalty_scale * lipschitz), dtype=dtype))
        self.kappa = nn.Parameter(torch.full((config.iterations,), config.kappa_init,
                                             dtype=dtype))
        self.kernel_param = build_parameterisation(
            config.kernel_param, physics.kernels.detach(), config.kernel_support_dilate,
            config.flow_grid, config.flow_residual, config.kernel_gain)
        if self.kernel_param is not None:
            physics.kernels.requires_grad_(False)
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
        """``A_θ``: the network's forward model with its current kernels (differentiable while
        training): the eigen-kernel model, or ``Kbase`` alone when no step uses it (``base``).
        """
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
