r"""Measurement consistency: the fit-pairs objective as a training loss (research; was
``ekdun train --physics-weight``, now ``research.kernel_models.train(physics_weight=λ)``).

It gives EK-DUN's kernels a gradient straight from the training pairs
(research/notes/compare-studies.md):

.. math::

    \mathcal{L}_{\mathrm{phys}} = \frac{1}{B} \sum_b
        \frac{\lVert s_b A_\theta x_b - y_b \rVert^2}{\lVert y_b \rVert^2},
    \qquad s_b = \frac{\langle A_\theta x_b, y_b\rangle}{\lVert A_\theta x_b\rVert^2},

with ``A_θ`` the network's own forward model; training minimises ``MSE(x̂, x) + λ · L_phys``.
It is computed in float32 outside autocast, inside ``forward`` so that DDP sees every use of
the kernels.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ekdun.errors import ConfigurationError


def measurement_consistency(prediction: Tensor, y: Tensor) -> Tensor:
    """Mean over the batch of ``‖s_b p_b − y_b‖² / ‖y_b‖²`` with the best scale ``s_b``, for
    ``prediction`` (``A_θ x``) and ``y`` ``(B, C, H', W')``: a scalar."""
    p = prediction.flatten(1)
    m = y.flatten(1).to(p.dtype)
    pp = (p * p).sum(1).clamp_min(torch.finfo(p.dtype).tiny)
    py = (p * m).sum(1)
    yy = (m * m).sum(1).clamp_min(torch.finfo(p.dtype).tiny)
    scale = py / pp
    residual = ((scale[:, None] * p - m) ** 2).sum(1)
    return (residual / yy).mean()


class PhysicsObjective(nn.Module):
    """``(y, x) → (x̂, weight · L_phys)`` for an EK-DUN (its :meth:`forward_model` gives
    ``A_θ``): the ``objective`` of :class:`ekdun.training.TrainOptions`."""

    def __init__(self, network: nn.Module, weight: float = 1.0) -> None:
        super().__init__()
        if not hasattr(network, "forward_model"):
            raise ConfigurationError("physics_weight needs a network with its own eigen-"
                                     "kernel forward model (EK-DUN)")
        self.network = network
        self.weight = weight

    def forward(self, y: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
        out = self.network(y)
        with torch.autocast(y.device.type, enabled=False):
            op = self.network.forward_model()
            consistency = measurement_consistency(op.A(x.float()), y.float())
        return out, self.weight * consistency
