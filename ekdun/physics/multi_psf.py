"""UPDN's learned PSF stack as an operator: ``N`` PSFs per colour, each on its own channel."""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

from ekdun.errors import KernelShapeError, TensorShapeError
from ekdun.physics.operators import FFTConvolutionOperator


class MultiPSFOperator(FFTConvolutionOperator):
    r"""``N`` PSFs per colour, each convolving its own channel (UPDN's learned PSF stack):
    channel ``n·C + c`` of the ``(B, N·C, H', W')`` input with ``psfs[n, c]``.

    Parameters
    ----------
    psfs : Tensor
        ``(N, C, Hk, Wk)``.
    sensor_shape : (int, int), optional
        Default the PSFs' size.
    scene_padding : int
    trainable : bool
    """

    def __init__(self, psfs: Tensor, sensor_shape: Sequence[int] | None = None,
                 scene_padding: int = 2, trainable: bool = True) -> None:
        if psfs.ndim != 4:
            raise KernelShapeError(f"a PSF stack must be (N, C, H, W), got shape "
                                   f"{tuple(psfs.shape)}")
        sensor = tuple(psfs.shape[-2:]) if sensor_shape is None else sensor_shape
        self.copies = int(psfs.shape[0])
        self.colours = int(psfs.shape[1])
        flat = psfs.reshape(1, self.copies * self.colours, *psfs.shape[-2:])
        super().__init__(flat, None, sensor, "sensor", scene_padding, trainable)

    @property
    def psfs(self) -> Tensor:
        """``(N, C, Hk, Wk)`` view of the PSF stack."""
        return self.kernels.reshape(self.copies, self.colours, *self.kernels.shape[-2:])

    def tile(self, y: Tensor) -> Tensor:
        """``(B, C, H', W') → (B, N·C, H', W')``: the measurement once per PSF copy."""
        if y.ndim != 4 or int(y.shape[1]) != self.colours:
            raise TensorShapeError(f"measurement must be (B, {self.colours}, H, W), got shape "
                                   f"{tuple(y.shape)}")
        return y.repeat(1, self.copies, 1, 1)
