r"""Measurement consistency: the fit-pairs objective as a training loss.

EK-DUN's kernels get a gradient only through the reconstruction loss, which at the bench's
scale is 24× weaker for ``Kv``/``Kh`` than for ``Kbase``
(research/notes/compare-studies.md). The measurement-consistency term gives them one
straight from the training pairs:

.. math::

    \mathcal{L}_{\mathrm{phys}} = \frac{1}{B} \sum_b
        \frac{\lVert s_b A_\theta x_b - y_b \rVert^2}{\lVert y_b \rVert^2},
    \qquad s_b = \frac{\langle A_\theta x_b, y_b\rangle}{\lVert A_\theta x_b\rVert^2},

with ``A_θ`` the network's own forward model (the eigen-kernel model of its last iteration,
``Kbase`` alone for the ``base`` schedule) and ``s_b`` the per-pair scale of ``psfkit
fit-pairs`` in closed form (by the envelope theorem its gradient needs no extra term).
Training minimises ``MSE(x̂, x) + λ · L_phys`` (``--physics-weight λ``; 0 is the paper's loss).

The term is computed in float32 outside autocast (the FFTs of the physics stay float32 under
AMP) and inside the module's ``forward``, so that DistributedDataParallel sees every use of
the kernels in the one forward pass it wraps.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ekdun.errors import ConfigurationError


def measurement_consistency(prediction: Tensor, y: Tensor) -> Tensor:
    """Mean over the batch of ``‖s_b p_b − y_b‖² / ‖y_b‖²`` with the best scale ``s_b``.

    Parameters
    ----------
    prediction, y : Tensor ``(B, C, H', W')``
        ``A_θ x`` and the measurement.

    Returns
    -------
    Tensor
        Scalar, float32 (or the inputs' wider dtype); 0 for a perfect model up to scale.
    """
    p = prediction.flatten(1)
    m = y.flatten(1).to(p.dtype)
    pp = (p * p).sum(1).clamp_min(torch.finfo(p.dtype).tiny)
    py = (p * m).sum(1)
    yy = (m * m).sum(1).clamp_min(torch.finfo(p.dtype).tiny)
    scale = py / pp
    residual = ((scale[:, None] * p - m) ** 2).sum(1)
    return (residual / yy).mean()


class PhysicsObjective(nn.Module):
    """``(x, y) → (x̂, L_phys)``: the network's reconstruction and its measurement consistency.

    Parameters
    ----------
    network : nn.Module
        An EK-DUN (:class:`ekdun.nets.ekdun_net.EKDUN`); its :meth:`forward_model` gives
        ``A_θ`` with differentiable kernels.
    """

    def __init__(self, network: nn.Module) -> None:
        super().__init__()
        if not hasattr(network, "forward_model"):
            raise ConfigurationError("--physics-weight needs a network with its own eigen-"
                                     "kernel forward model (--network ekdun)")
        self.network = network

    def forward(self, y: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
        out = self.network(y)
        with torch.autocast(y.device.type, enabled=False):
            op = self.network.forward_model()
            consistency = measurement_consistency(op.A(x.float()), y.float())
        return out, consistency
