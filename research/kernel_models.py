r"""EK-DUN kernel parameterisations (research; was ``ekdun train --kernel-param``, issue 44).

The product trains free pixels; a study plugs a module in through the product's hooks
(:meth:`ekdun.nets.ekdun_net.EKDUN.use_kernel_module`, ``TrainOptions.model_hook``):
:func:`attach`, :func:`build_network`, :func:`train` and :func:`network_from_checkpoint` here
take the old override names (:data:`SETTINGS`) and ``physics_weight``
(:mod:`research.physics_loss`).

* ``"free"``: every kernel pixel is a parameter (the paper's; nothing here is used).
* ``"physical"`` (:class:`PhysicalKernels`): ``K = E · softmax_S(θ)`` per kernel and channel:
  non-negative, zero outside the seed's dilated caustic ``S``, with the seed's energy ``E``
  kept; ``θ`` starts at ``log(max(seed, 0) + floor)``, so steps change pixels by factors.
* ``"flow"`` (:class:`FlowKernels`): ``Kbase`` as ``"physical"``; correction kernels
  ``K_j(x) = g_{j,c} · Kbase(x − D_j(x)) [+ S · R_j]`` with ``D_j`` a smooth displacement field
  from a coarse grid (bicubic), ``g`` a per-channel gain and ``R_j`` an optional residual,
  fitted to the seed first (:meth:`FlowKernels.fit_to`).

These parameters are O(1), so their optimiser group gets :data:`LR_MULTIPLIER` (the
module's ``lr_multiplier``; research/notes/compare-studies.md).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import replace
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ekdun.errors import ConfigurationError
from ekdun.nets import builder
from ekdun.nets.ekdun_net import EKDUN
from ekdun.nets.unrolled import UnrolledNetwork
from ekdun.training import TrainOptions
from ekdun.training import train as product_train
from psfkit.forward.kernelfile import KernelModel
from research.compare.displacement import caustic_support
from research.physics_loss import PhysicsObjective

#: Parameterisations ``EKDUNConfig.kernel_param`` accepts.
KERNEL_PARAMETERISATIONS = ("free", "physical", "flow")

#: Multiplier of ``TrainingConfig.kernel_lr_scale`` (1e-2 of the network's rate) for the
#: kernel parameter group: free pixels 1 (unchanged), log-intensities and displacements
#: (px) 100, i.e. the network's rate (tiny preset: 2e-3 per Adam step; over 360 steps a
#: field can move ~0.7 px, the size of the measured displacements). Chosen by the lr sweep.
LR_MULTIPLIER = {"free": 1.0, "physical": 100.0, "flow": 100.0}


def seed_support(kernels: Tensor, level: float = 0.02, dilate: int = 3) -> Tensor:
    """Dilated caustic support of kernels ``(K, C, H, W)``: ``(H, W)`` bool, the union over
    kernels (:func:`research.compare.displacement.caustic_support`)."""
    k = kernels.detach().cpu().numpy().astype(np.float32)
    return torch.as_tensor(caustic_support(k, level, dilate))


class PhysicalKernels(nn.Module):
    """Non-negative kernels on a fixed support with fixed per-(kernel, channel) energy.

    Parameters
    ----------
    seed : Tensor
        ``(K, C, H, W)`` initial kernels.
    support : Tensor
        ``(H, W)`` bool.
    floor : float
        Relative floor (of each kernel's peak) added to the seed before taking logs.
    gain : bool
        Give the correction kernels a learned per-channel gain ``exp(·)`` (from 1).
    """

    name = "physical"
    lr_multiplier = LR_MULTIPLIER["physical"]

    def __init__(self, seed: Tensor, support: Tensor, floor: float = 1e-6,
                 gain: bool = False) -> None:
        super().__init__()
        if seed.ndim != 4 or tuple(support.shape) != tuple(seed.shape[-2:]):
            raise ConfigurationError("physical kernels need (K, C, H, W) seeds and an (H, W) "
                                     "support")
        if not bool(support.any()):
            raise ConfigurationError("the seed kernels have an empty caustic support")
        mask = support.to(seed.dtype)
        positive = seed.detach().clamp(min=0) * mask
        energy = positive.sum(dim=(-2, -1), keepdim=True)
        if bool((energy <= 0).any()):
            raise ConfigurationError("a seed kernel has no positive energy on its support")
        peak = positive.amax(dim=(-2, -1), keepdim=True)
        self.register_buffer("support", support.clone())
        self.register_buffer("energy", energy)
        self.logits = nn.Parameter(torch.log(positive + floor * peak))
        self.log_gain = (nn.Parameter(seed.new_zeros((seed.shape[0] - 1, seed.shape[1])))
                         if gain else None)

    def forward(self) -> Tensor:
        """The kernels ``(K, C, H, W)``."""
        k, c, h, w = self.logits.shape
        masked = self.logits.masked_fill(~self.support, float("-inf"))
        kernels = self.energy * torch.softmax(masked.reshape(k, c, h * w), dim=-1).reshape(
            k, c, h, w)
        if self.log_gain is None:
            return kernels
        gains = torch.cat([self.log_gain.new_zeros((1, c)), self.log_gain]).exp()
        return kernels * gains[:, :, None, None]


def warp_bilinear(image: Tensor, displacement: Tensor) -> Tensor:
    """``image(x − D(x))`` ``(N, C, H, W)`` by bilinear interpolation, zero outside, exact
    where ``D = 0``, for ``image`` ``(C, H, W)`` and ``displacement`` ``(N, 2, H, W)`` px
    (``(D_u, D_v)``, u = column)."""
    c, h, w = image.shape
    yy, xx = torch.meshgrid(torch.arange(h, dtype=image.dtype, device=image.device),
                            torch.arange(w, dtype=image.dtype, device=image.device),
                            indexing="ij")
    py = yy - displacement[:, 1]
    px = xx - displacement[:, 0]
    y0, x0 = torch.floor(py), torch.floor(px)
    wy, wx = py - y0, px - x0
    flat = image.reshape(c, h * w)
    out = image.new_zeros((c, *py.shape))
    for dy, fy in ((0, 1 - wy), (1, wy)):
        for dx, fx in ((0, 1 - wx), (1, wx)):
            yi, xi = y0 + dy, x0 + dx
            valid = (yi >= 0) & (yi < h) & (xi >= 0) & (xi < w)
            index = (yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).long()
            out = out + flat[:, index] * (fy * fx * valid)
    return out.transpose(0, 1)


class FlowKernels(nn.Module):
    """``Kbase`` (physical) and correction kernels = gain × ``Kbase`` warped by smooth fields.

    Parameters
    ----------
    seed : Tensor
        ``(K, C, H, W)``; ``seed[0]`` is ``Kbase``.
    support : Tensor
        ``(H, W)`` bool.
    grid : int
        Size ``n`` of the coarse ``n × n`` displacement grid.
    residual : bool
        Add a trainable residual on the support.
    """

    name = "flow"
    lr_multiplier = LR_MULTIPLIER["flow"]

    def __init__(self, seed: Tensor, support: Tensor, grid: int = 8,
                 residual: bool = False) -> None:
        super().__init__()
        if seed.shape[0] < 2:
            raise ConfigurationError("flow kernels need a base and at least one correction "
                                     "kernel")
        if grid < 2:
            raise ConfigurationError(f"flow grid must be >= 2, got {grid}")
        n, c = seed.shape[0] - 1, seed.shape[1]
        self.base = PhysicalKernels(seed[:1], support)
        self.field = nn.Parameter(seed.new_zeros((n, 2, grid, grid)))
        self.log_gain = nn.Parameter(seed.new_zeros((n, c)))
        self.residual = (nn.Parameter(seed.new_zeros((n, c, *seed.shape[-2:])))
                         if residual else None)

    def displacement(self) -> Tensor:
        """Dense fields ``(N, 2, H, W)`` px (bicubic upsampling of the coarse grid)."""
        return F.interpolate(self.field, size=tuple(self.base.support.shape), mode="bicubic",
                             align_corners=True)

    def forward(self) -> Tensor:
        """The kernels ``(K, C, H, W)``."""
        base = self.base()
        moved = warp_bilinear(base[0], self.displacement())
        corrections = self.log_gain.exp()[:, :, None, None] * moved
        if self.residual is not None:
            corrections = corrections + self.residual * self.base.support
        return torch.cat([base, corrections])

    def fit_to(self, seed: Tensor, steps: int = 300, lr: float = 0.05) -> float:
        """Fit fields and gains (and residual) to a seed's correction kernels (nothing when
        they equal ``Kbase``); the relative L2 error of the flow without the residual."""
        target = seed[1:].detach()
        if torch.equal(target, seed[:1].expand_as(target)):
            return 0.0
        params = [self.field, self.log_gain]
        opt = torch.optim.Adam(params, lr=lr)
        residual, self.residual = self.residual, None
        try:
            for _ in range(steps):
                opt.zero_grad()
                loss = ((self()[1:] - target) ** 2).sum()
                loss.backward()
                opt.step()
            with torch.no_grad():
                fitted = self()[1:]
                error = float((fitted - target).norm() / target.norm())
        finally:
            self.residual = residual
        if self.residual is not None:
            with torch.no_grad():
                self.residual.copy_((target - fitted) * self.base.support)
        return error


def build_parameterisation(name: str, seed: Tensor, dilate: int = 3, flow_grid: int = 8,
                           flow_residual: bool = False, gain: bool = False
                           ) -> nn.Module | None:
    """The module that makes the kernels (``None`` for ``"free"``) from seed ``(K, C, H, W)``;
    :class:`ConfigurationError` for an unknown name or a seed it cannot represent."""
    if name not in KERNEL_PARAMETERISATIONS:
        raise ConfigurationError(f"unknown kernel parameterisation {name!r} (use "
                                 f"{', '.join(KERNEL_PARAMETERISATIONS)})")
    if name == "free":
        return None
    support = seed_support(seed, dilate=dilate).to(seed.device)
    if name == "physical":
        return PhysicalKernels(seed, support, gain=gain)
    flow = FlowKernels(seed, support, flow_grid, flow_residual)
    flow.fit_to(seed)
    return flow


#: The study's EK-DUN settings (once ``EKDUNConfig`` fields) and their defaults.
SETTINGS = {"kernel_param": "free", "kernel_support_dilate": 3, "flow_grid": 8,
            "flow_residual": False, "kernel_gain": False}


def split_overrides(overrides: dict[str, Any] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(product overrides, study settings)`` of overrides that may hold :data:`SETTINGS`."""
    overrides = dict(overrides or {})
    study = {k: overrides.pop(k) for k in SETTINGS if k in overrides}
    return overrides, study


def attach(model: UnrolledNetwork, kernel_param: str = "free", kernel_support_dilate: int = 3,
           flow_grid: int = 8, flow_residual: bool = False, kernel_gain: bool = False) -> None:
    """Give an EK-DUN the kernel module ``kernel_param`` (nothing for ``"free"``)."""
    if kernel_param == "free":
        return
    if not isinstance(model, EKDUN):
        raise ConfigurationError(f"kernel_param {kernel_param!r} applies to EK-DUN only")
    module = build_parameterisation(kernel_param, model.physics.kernels.detach(),
                                    kernel_support_dilate, flow_grid, flow_residual,
                                    kernel_gain)
    assert module is not None
    model.use_kernel_module(module)


def build_network(name: str, seed: KernelModel, preset: str,
                  overrides: dict[str, Any] | None = None) -> UnrolledNetwork:
    """:func:`ekdun.nets.builder.build_network` taking :data:`SETTINGS` among ``overrides``."""
    product, study = split_overrides(overrides)
    model = builder.build_network(name, seed, preset, product)
    attach(model, **study)
    return model


def train(run_dir: str | os.PathLike, model_name: str, seed: Any, dataset: Any,
          preset: str = "tiny", overrides: dict[str, Any] | None = None,
          options: TrainOptions | None = None, physics_weight: float = 0.0,
          **kwargs: Any) -> dict[str, Any]:
    """:func:`ekdun.training.train` with :data:`SETTINGS` among ``overrides`` and the
    measurement-consistency weight λ (was ``--physics-weight``); both are recorded as the
    metadata's ``study``, λ's term in the history as ``physics_loss``."""
    weight = float(physics_weight)
    if not math.isfinite(weight) or weight < 0:
        raise ConfigurationError(f"physics_weight must be a finite number >= 0, got "
                                 f"{physics_weight!r}")
    product, study = split_overrides(overrides)

    def hook(model: UnrolledNetwork) -> None:
        if weight > 0 and not hasattr(model, "forward_model"):
            raise ConfigurationError(f"physics_weight needs EK-DUN's own eigen-kernel forward "
                                     f"model; {model_name} has none")
        attach(model, **study)

    options = replace(options or TrainOptions(), model_hook=hook,
                      objective=(lambda m: PhysicsObjective(m, weight)) if weight > 0 else None,
                      study={**study, "physics_weight": weight})
    result = product_train(run_dir, model_name, seed, dataset, preset, product, options,
                           **kwargs)
    for row in result["history"]:
        if "extra_loss" in row:
            row["physics_loss"] = row["extra_loss"] / weight
    return result


def recorded(meta: dict[str, Any]) -> tuple[dict[str, Any], float]:
    """``(overrides with the study's settings, λ)`` a run's metadata records (both places:
    ``study`` now, ``overrides`` and ``training`` before)."""
    study = meta.get("study") or {}
    overrides = {**meta.get("overrides", {}), **{k: v for k, v in study.items() if k in SETTINGS}}
    weight = study.get("physics_weight", (meta.get("training") or {}).get("physics_weight"))
    return overrides, float(weight or 0.0)


def network_from_checkpoint(checkpoint: str | os.PathLike | dict[str, Any]
                            ) -> tuple[UnrolledNetwork, dict[str, Any]]:
    """:func:`ekdun.nets.builder.network_from_checkpoint` with the run's kernel module."""
    model, doc = builder.network_from_checkpoint(checkpoint)
    _, study = split_overrides(recorded(doc["metadata"])[0])
    attach(model, **study)
    model.load_state_dict(doc["model"])
    return model, doc


def main(argv: list[str] | None = None) -> int:
    """``python -m research.kernel_models ARGS``: ``ekdun train ARGS`` that also takes the
    study's ``--kernel-param`` and ``--physics-weight`` (research/scale_experiment.sh)."""
    import ekdun.training
    from ekdun.cli import main as ekdun_main

    parser = argparse.ArgumentParser(allow_abbrev=False, add_help=False)
    parser.add_argument("--kernel-param", choices=KERNEL_PARAMETERISATIONS, default="free")
    parser.add_argument("--physics-weight", type=float, default=0.0)
    study, rest = parser.parse_known_args(argv)

    def run(run_dir: Any, model_name: str, seed: Any, dataset: Any, preset: str,
            overrides: dict[str, Any], options: TrainOptions, **kwargs: Any) -> dict[str, Any]:
        return train(run_dir, model_name, seed, dataset, preset,
                     {**overrides, "kernel_param": study.kernel_param}, options,
                     physics_weight=study.physics_weight, **kwargs)

    ekdun.training.train = run      # what ekdun train calls, in this process only
    return ekdun_main(["train", *rest])


if __name__ == "__main__":
    sys.exit(main())
