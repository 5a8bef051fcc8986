r"""The forward model with the scene on the whole padded grid (light from outside the view).

A real measurement also records scene points outside the ``H' × W'`` field that the sensor-sized
model ``y = Σ_k W_k ⊙ crop(K_k * pad(x))`` assumes; a reconstruction restricted to that field
has to explain their light with in-field pixels (artefacts at the borders). ADMM-TV
(:mod:`ekdun.reconstruction.admm_tv`) therefore solves on the padded grid, and so can PDHG with
this operator, for sensor-side eigen-kernel models (the weights multiply each kernel's image
on the sensor, so they need no values outside it)::

    A x  = Σ_k W_k ⊙ crop(K_k * x)          x: (B, C, PH, PW),  1 + K FFTs
    Aᵀ y = Σ_k K_k ⋆ pad(W_k ⊙ y)           K + 1 FFTs

``A pad(x)`` equals the sensor-sized model's ``A x`` (tested). Every FFT goes through
:mod:`psfkit.forward.fft`.
"""

from __future__ import annotations

from torch import Tensor

from ekdun.errors import ConfigurationError, TensorShapeError
from psfkit.forward.convolution import crop, pad
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.operator import SpectralOperator


class ExtendedSceneOperator:
    """``A`` and ``Aᵀ`` of a sensor-side model with the scene on the padded grid.

    Parameters
    ----------
    base : SpectralOperator
        A prepared eigen-kernel or shift-invariant operator (its spectra, weights and grid).

    Raises
    ------
    ConfigurationError
        A source-side model (its weights are defined on the sensor-sized scene only).
    """

    def __init__(self, base: SpectralOperator) -> None:
        self.weights = base.weights
        if self.weights is not None and bool((self.weights == 1).all()):
            self.weights = None                 # shift-invariant: either convention
        if self.weights is not None and base.convention != "sensor":
            raise ConfigurationError("the extended scene needs a sensor-side model (the weights "
                                     "of a source-side model exist only inside the view)")
        self.base = base
        self.sensor_shape = base.sensor_shape
        self.grid_shape = base.grid_shape
        self.channels = base.channels
        self.dtype = base.dtype

    def check(self, y: Tensor, what: str) -> None:
        """Raise :class:`~ekdun.errors.TensorShapeError` unless ``y`` is a ``(B, C, H', W')``
        measurement of this model."""
        if y.ndim != 4 or tuple(y.shape[-2:]) != self.sensor_shape \
                or int(y.shape[1]) != self.channels or y.dtype != self.dtype:
            raise TensorShapeError(f"{what} must be (B, {self.channels}, {self.sensor_shape[0]}, "
                                   f"{self.sensor_shape[1]}) {self.dtype}, got "
                                   f"{tuple(y.shape)} {y.dtype}")

    def A(self, x: Tensor) -> Tensor:
        """Scene ``(B, C, PH, PW)`` → measurement ``(B, C, H', W')``."""
        spectrum = rfft2(x)[:, None]                               # (B, 1, C, PH, PW//2+1)
        images = crop(irfft2(self.base.spectra * spectrum, self.grid_shape),
                      self.sensor_shape)                           # (B, K, C, H', W')
        if self.weights is None:
            return images.sum(dim=1)
        return (images * self.weights[None, :, None]).sum(dim=1)

    def A_adjoint(self, y: Tensor) -> Tensor:
        """Measurement ``(B, C, H', W')`` → scene ``(B, C, PH, PW)``."""
        if self.weights is None:
            weighted = y[:, None]
        else:
            weighted = y[:, None] * self.weights[None, :, None]        # (B, K, C, H', W')
        spectra = rfft2(pad(weighted, self.grid_shape))
        total = (self.base.conj_spectra * spectra).sum(dim=1)
        return irfft2(total, self.grid_shape)

    def crop(self, x: Tensor) -> Tensor:
        """The sensor-sized central block of a padded-grid scene."""
        return crop(x, self.sensor_shape).contiguous()

    def pad(self, x: Tensor) -> Tensor:
        """A sensor-sized scene zero-filled into the padded grid."""
        return pad(x, self.grid_shape)

