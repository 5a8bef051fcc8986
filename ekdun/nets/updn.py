r"""UPDN (Kingshott et al. 2022): unrolled primal-dual network with learned PSFs, then a U-Net.

Learned primal-dual (Adler & Öktem) with the multi-PSF operator ``A`` of ``N`` PSFs per colour
(paper: 5, so 15 channels for RGB), every PSF initialised from the measured one. Primal ``p``
and dual ``q`` both have ``N·C`` channels and the sensor's size; the measurement is tiled to
``ỹ = (y, …, y)``. Iteration ``i``:

.. math::

    q &\leftarrow q + \Gamma^{(i)}\big([A p,\ q,\ \tilde y]\big) \\
    p &\leftarrow p + \Lambda^{(i)}\big([A^\top q,\ p]\big)

``Γ⁽ⁱ⁾`` is ``Conv3×3 (groups = N) → ReLU → Conv1×1`` from ``3·N·C`` to ``N·C`` channels and
``Λ⁽ⁱ⁾`` the same from ``2·N·C``; the inputs are interleaved per PSF copy so that each 3×3 group
sees one copy's ``(A p, q, ỹ)`` (resp. ``(Aᵀq, p)``), and the ``1×1`` convolution mixes the
copies. ``p`` and ``q`` start at zero. The output is ``p[:, :C] + U-Net(p)``.

Following ``oliland/lensless-primal-dual`` (``ImageOptimizerMixColors``): 5 tiled PSFs, 10
primal-dual blocks of this form, a U-Net on the primal channels with a residual on the first
copy. Differences: the primal lives on the sensor-sized scene grid (our convention, ``x`` and
``y`` both ``H' × W'``) instead of the padded grid, the groups are aligned with the PSF copies,
and there is no output sigmoid (as for the other models, the loss sees linear values). The PSF
copies are identical at initialisation; they diverge in training because each copy's group of
the convolutions has its own random weights.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from ekdun.nets.configs import UPDNConfig
from ekdun.nets.unet import UNet, channels_last
from ekdun.nets.unrolled import State, UnrolledNetwork
from ekdun.physics.multi_psf import MultiPSFOperator


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
        Iterations (10), hidden width and the U-Net.
    """

    def __init__(self, physics: MultiPSFOperator, config: UPDNConfig | None = None) -> None:
        config = config or UPDNConfig()
        super().__init__(config.iterations)
        self.config = config
        self.physics = physics
        n, width = physics.copies, physics.channels
        self.dual_updates = nn.ModuleList(
            update_block(n, 3 * width, width, config.hidden_factor)
            for _ in range(config.iterations))
        self.primal_updates = nn.ModuleList(
            update_block(n, 2 * width, width, config.hidden_factor)
            for _ in range(config.iterations))
        self.denoiser = UNet(width, physics.colours, config.denoiser.widths,
                             config.denoiser.residual, config.denoiser.zero_init_output)

    def prepare(self, y: Tensor) -> dict[str, Any]:
        op = self.physics.prepare()
        tiled = self.physics.tile(y)
        op.check(tiled, "measurement (tiled per PSF copy)")
        return {"op": op, "y": tiled}

    def initial_state(self, y: Tensor, context: dict[str, Any]) -> State:
        zeros = torch.zeros_like(context["y"])
        return {"primal": zeros, "dual": zeros}

    def update(self, i: int, state: State, context: dict[str, Any]) -> State:
        op, n = context["op"], self.physics.copies
        primal, dual = state["primal"], state["dual"]
        # the convolutions run channels-last; the FFTs of A and Aᵀ want contiguous planes
        dual = dual + channels_last(self.dual_updates[i],
                                    interleave_copies(n, op.A(primal), dual, context["y"]))
        primal = primal + channels_last(self.primal_updates[i],
                                        interleave_copies(n, op.A_adjoint(dual), primal))
        return {"primal": primal, "dual": dual}

    def output(self, state: State, context: dict[str, Any]) -> Tensor:
        return self.denoiser(state["primal"])
