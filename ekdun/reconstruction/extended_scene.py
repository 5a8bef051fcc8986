r"""The forward model with the scene on the whole padded grid (light from outside the view).

A real measurement also records scene points outside the ``H' × W'`` field that the sensor-sized
model ``y = Σ_k W_k ⊙ crop(K_k * pad(x))`` assumes; a reconstruction restricted to that field
has to explain their light with in-field pixels (artefacts at the borders). ADMM-TV
(:mod:`ekdun.reconstruction.admm_tv`) therefore solves on the padded grid, and so can PDHG with
this operator. Sensor-side eigen-kernel models need nothing more (their weights multiply each
kernel's image on the sensor); source-side ones weight the scene, so they need weights on the
whole grid: :meth:`psfkit.kernelfile.KernelModel.weight_maps` with ``extent``, which continues
the edge weights outside the view (the model is fitted on the view only)::

    sensor side:  A x = Σ_k W_k ⊙ crop(K_k * x)       Aᵀ y = Σ_k K_k ⋆ pad(W_k ⊙ y)
                  1 + K FFTs                           K + 1 FFTs
    source side:  A x = crop(Σ_k K_k * (V_k ⊙ x))     Aᵀ y = Σ_k V_k ⊙ (K_k ⋆ pad(y))
                  K + 1 FFTs                           1 + K FFTs

for ``x`` ``(B, C, PH, PW)`` and ``V_k`` the ``(PH, PW)`` scene weights. ``A pad(x)`` equals the
sensor-sized model's ``A x`` (tested). Every FFT goes through :mod:`psfkit.forward.fft`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, TensorShapeError
from ekdun.physics.operators import EigenKernelOperator
from psfkit.forward.convolution import crop, pad
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.operator import SpectralOperator
from psfkit.kernelfile import KernelModel


class ExtendedSceneOperator:
    """``A`` and ``Aᵀ`` of an eigen-kernel model with the scene on the padded grid.

    Parameters
    ----------
    base : SpectralOperator
        A prepared eigen-kernel or shift-invariant operator (its spectra, weights and grid).
    scene_weights : Tensor, optional
        ``(K, PH, PW)`` weights of a source-side model on the padded grid, whose central
        ``H' × W'`` block is ``base.weights`` (:meth:`from_kernel_model` builds them); not
        used by sensor-side and shift-invariant models.

    Raises
    ------
    ConfigurationError
        A source-side eigen-kernel model without ``scene_weights``, or weights that do not
        match the model's in the view.
    """

    def __init__(self, base: SpectralOperator, scene_weights: Tensor | None = None) -> None:
        self.weights = base.weights
        if self.weights is not None and bool((self.weights == 1).all()):
            self.weights = None                 # shift-invariant: either convention
        self.convention = "sensor" if self.weights is None else base.convention
        self.base = base
        self.sensor_shape = base.sensor_shape
        self.grid_shape = base.grid_shape
        self.channels = base.channels
        self.dtype = base.dtype
        self.scene_weights: Tensor | None = None
        if self.convention == "source":
            if scene_weights is None:
                raise ConfigurationError(
                    "the extended scene of a source-side model needs its weights on the padded "
                    "grid (ExtendedSceneOperator.from_kernel_model builds them)")
            shape = (int(base.spectra.shape[0]), *self.grid_shape)
            if tuple(scene_weights.shape) != shape or not torch.allclose(
                    crop(scene_weights, self.sensor_shape), self.weights.to(scene_weights.dtype),
                    rtol=1e-5, atol=1e-6):
                raise ConfigurationError(
                    f"scene weights must be {shape} and equal the model's weights in the view")
            self.scene_weights = scene_weights.to(self.dtype).contiguous()

    @classmethod
    def from_kernel_model(cls, model: KernelModel, dtype: torch.dtype = torch.float32
                          ) -> ExtendedSceneOperator:
        """The extended-scene operator of a kernel file's model (either convention)."""
        base = EigenKernelOperator.from_kernel_model(model, dtype=dtype).prepare()
        scene_weights = None
        if model.convention == "source" and model.kernels.shape[0] > 1:
            scene_weights = torch.as_tensor(model.weight_maps(extent=base.grid_shape),
                                            dtype=dtype)
        return cls(base, scene_weights)

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
        if self.scene_weights is not None:                 # source side: weight, then blur
            spectra = rfft2(x[:, None] * self.scene_weights[None, :, None])
            return crop(irfft2((self.base.spectra * spectra).sum(dim=1), self.grid_shape),
                        self.sensor_shape)
        spectrum = rfft2(x)[:, None]                               # (B, 1, C, PH, PW//2+1)
        images = crop(irfft2(self.base.spectra * spectrum, self.grid_shape),
                      self.sensor_shape)                           # (B, K, C, H', W')
        if self.weights is None:
            return images.sum(dim=1)
        return (images * self.weights[None, :, None]).sum(dim=1)

    def A_adjoint(self, y: Tensor) -> Tensor:
        """Measurement ``(B, C, H', W')`` → scene ``(B, C, PH, PW)``."""
        if self.scene_weights is not None:
            spectrum = rfft2(pad(y, self.grid_shape))[:, None]
            images = irfft2(self.base.conj_spectra * spectrum, self.grid_shape)
            return (images * self.scene_weights[None, :, None]).sum(dim=1)
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

