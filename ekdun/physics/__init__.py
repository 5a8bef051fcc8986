"""Physics layer of ekdun: :class:`torch.nn.Module` forward operators with exact adjoints,
wrapping the one forward model, :mod:`psfkit.forward`.
"""

from ekdun.physics.multi_psf import MultiPSFOperator
from ekdun.physics.operators import (
    EigenKernelOperator,
    FFTConvolutionOperator,
    PreparedOperator,
    ShiftInvariantOperator,
)

__all__ = ["EigenKernelOperator", "FFTConvolutionOperator", "MultiPSFOperator", "PreparedOperator",
           "ShiftInvariantOperator"]
