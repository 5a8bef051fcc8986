"""Physics layer of ekdun: lensless forward operators with exact adjoints.

The forward model itself (pad, crop, kernel embedding and spectra, FFT convolution and
correlation, Eq. 7 in both conventions) lives in :mod:`psfkit.forward`;
:mod:`ekdun.physics.operators` holds the :class:`torch.nn.Module` operator classes wrapping it.
"""

from ekdun.physics.multi_psf import MultiPSFOperator
from ekdun.physics.operators import (
    EigenKernelOperator,
    FFTConvolutionOperator,
    PreparedOperator,
    ShiftInvariantOperator,
)

__all__ = [
    "EigenKernelOperator",
    "FFTConvolutionOperator",
    "MultiPSFOperator",
    "PreparedOperator",
    "ShiftInvariantOperator",
]
