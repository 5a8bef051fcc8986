"""Physics layer of ekdun: lensless forward operators with exact adjoints.

:mod:`ekdun.physics.functional` holds the pure FFT kernels (pad, crop, kernel embedding,
spectra, convolution and correlation); :mod:`ekdun.physics.operators` the operator classes.
"""

from ekdun.physics.operators import (
    EigenKernelOperator,
    FFTConvolutionOperator,
    MultiPSFOperator,
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
