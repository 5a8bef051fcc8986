r"""UPDN (Kingshott et al. 2022): unrolled primal-dual network with learned PSFs, then a U-Net.

Learned primal-dual (Adler & Öktem) with the multi-PSF operator ``A`` of ``N`` PSFs per colour.
Primal ``p`` and dual ``q`` have ``N·C`` channels; ``ỹ`` is the measurement tiled ``N`` times.
Iteration ``i``:

.. math::

    q &\leftarrow q + \Gamma^{(i)}\big([A p,\ q,\ \tilde y]\big) \\
    p &\leftarrow p + \Lambda^{(i)}\big([A^\top q,\ p]\big)

``Γ⁽ⁱ⁾``, ``Λ⁽ⁱ⁾``: ``Conv3×3 (groups = N) → ReLU → Conv1×1``, inputs interleaved per PSF copy.
``p``, ``q`` start at zero on the sensor (or, ``primal_grid="padded"``, ``p`` on the padded
scene grid with ``A p = crop(K ⊛ p)``, as the reference code); the output is
``p[:, :C] + U-Net(crop(p))``. Differences from ``oliland/lensless-primal-dual``
(docs/baselines.md): sensor primal by default, groups aligned with the copies, no output
sigmoid.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch
from torch import Tensor, nn

from ekdun.errors import ConfigurationError
from ekdun.nets.configs import UPDNConfig
from ekdun.nets.unet import UNet, channels_last
from ekdun.nets.unrolled import State, UnrolledNetwork
from ekdun.physics.multi_psf import MultiPSFOperator
from psfkit.forward.convolution import crop, pad
from psfkit.forward.padded_scene import padded_scene_adjoint, padded_scene_forward

#: Where UPDN's primal can live (:class:`~ekdun.nets.configs.UPDNConfig`).
PRIMAL_GRIDS = ("padded", "sensor")


def interleave_copies(copies: int, *tensors: Tensor) -> Tensor:
    """Concatenate ``(B, N·C, H, W)`` tensors per PSF copy: ``[t1_n, t2_n, …]`` for each n."""
    b, nc, h, w = tensors[0].shape
    stacked = torch.stack([t.reshape(b, copies, nc // copies, h, w) for t in tensors], dim=2)
    return stacked.reshape(b, copies * len(tensors) * (nc // copies), h, w)


def update_block(groups: int, in_channels: int, out_channels: int,
                 hidden_factor: int = 1) -> nn.Sequential:
    """``Conv3×3 (grouped) → ReLU → Conv1×1``: a primal or dual update of UPDN."""
    hidden = in_channels * hidden_factor
    return nn.Sequential(nn.Conv2d(in_channels, hidden, 3, padding=1, groups=groups),
                         nn.ReLU(inplace=True), nn.Conv2d(hidden, out_channels, 1))


class UPDN(UnrolledNetwork):
    """Unrolled primal-dual network baseline.

    Parameters
    ----------
    physics : MultiPSFOperator
        ``N`` trainable PSFs per colour.
    config : UPDNConfig
    """

    def __init__(self, physics: MultiPSFOperator, config: UPDNConfig | None = None) -> None:
        config = config or UPDNConfig()
        if config.primal_grid not in PRIMAL_GRIDS:
            raise ConfigurationError(f"UPDN primal_grid must be one of "
                                     f"{', '.join(PRIMAL_GRIDS)}, got {config.primal_grid!r}")
        super().__init__(physics, config)
        n, width = physics.copies, physics.channels
        self.dual_updates = nn.ModuleList(
            update_block(n, 3 * width, width, config.hidden_factor)
            for _ in range(config.iterations))
        self.primal_updates = nn.ModuleList(
            update_block(n, 2 * width, width, config.hidden_factor)
            for _ in range(config.iterations))
        self.denoiser = UNet(width, physics.colours, **asdict(config.denoiser))

    def prepare(self, y: Tensor) -> dict[str, Any]:
        op = self.physics.prepare()
        tiled = self.physics.tile(y)
        op.check(tiled, "measurement (tiled per PSF copy)")
        if self.config.primal_grid == "sensor":
            return {"op": op, "y": tiled, "A": op.A, "A_adjoint": op.A_adjoint}
        spectra, conj = op.spectra, op.conj_spectra                     # (1, N·C, PH, PW//2+1)
        grid, sensor = self.physics.grid_shape, self.physics.sensor_shape
        return {"op": op, "y": tiled,
                "A": lambda p: padded_scene_forward(p, spectra, None, sensor),
                "A_adjoint": lambda q: padded_scene_adjoint(q, conj, None, grid)}

    def initial_state(self, y: Tensor, context: dict[str, Any]) -> State:
        dual = torch.zeros_like(context["y"])
        if self.config.primal_grid == "sensor":
            return {"primal": dual, "dual": dual}
        return {"primal": pad(dual, self.physics.grid_shape), "dual": dual}

    def update(self, i: int, state: State, context: dict[str, Any]) -> State:
        n = self.physics.copies
        primal, dual = state["primal"], state["dual"]
        # Float32 whatever the autocast: the blocks add an increment to p and q ten times, and
        # A, Aᵀ sum a whole PSF's support, so half precision compounds (−8.6 dB
        # untrained at paper size on an H100). Only the U-Net runs under AMP, as in the other
        # networks. The convolutions run channels-last; the FFTs want contiguous planes.
        with torch.autocast(primal.device.type, enabled=False):
            dual = dual + channels_last(self.dual_updates[i],
                                        interleave_copies(n, context["A"](primal), dual,
                                                          context["y"]))
            primal = primal + channels_last(self.primal_updates[i],
                                            interleave_copies(n, context["A_adjoint"](dual),
                                                              primal))
        return {"primal": primal, "dual": dual}

    def output(self, state: State, context: dict[str, Any]) -> Tensor:
        return self.denoiser(crop(state["primal"], self.physics.sensor_shape))
