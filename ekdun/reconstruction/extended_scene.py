r"""The forward model with the scene on the whole padded grid (light from outside the view).

A real measurement also records scene points outside the ``H' × W'`` field that the sensor-sized
model ``y = Σ_k W_k ⊙ crop(K_k * pad(x))`` assumes; a reconstruction restricted to that field
has to explain their light with in-field pixels (artefacts at the borders). The ADMM-TV solver
(:mod:`ekdun.reconstruction.admm`) therefore solves on the padded grid, with this operator.
Sensor-side eigen-kernel models need
nothing more (their weights multiply each kernel's image on the sensor); source-side ones
weight the scene, so they need weights on the whole grid:
:meth:`psfkit.kernelfile.KernelModel.weight_maps` with ``extent``, which continues the edge
weights outside the view (the model is fitted on the view only).

The maths is :func:`psfkit.forward.convolution.padded_scene_forward` /
:func:`~psfkit.forward.convolution.padded_scene_adjoint` (Eq. 7, written once); this class
binds a model's spectra and weights to it and checks inputs. ``A pad(x)`` equals the
sensor-sized model's ``A x`` (tested).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, TensorShapeError
from ekdun.physics.operators import EigenKernelOperator
from psfkit.forward.convolution import (
    crop,
    pad,
    padded_scene_adjoint,
    padded_scene_forward,
)
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
        self.scene_shape = base.grid_shape          # the scene lives on the whole padded grid
        self.device = base.device
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
        return padded_scene_forward(x, self.base.spectra, self._weights(), self.sensor_shape,
                                    self.convention)

    def A_adjoint(self, y: Tensor) -> Tensor:
        """Measurement ``(B, C, H', W')`` → scene ``(B, C, PH, PW)``."""
        return padded_scene_adjoint(y, self.base.conj_spectra, self._weights(), self.grid_shape,
                                    self.convention)

    def _weights(self) -> Tensor | None:
        """The weights where they act: on the sensor (sensor side) or the padded scene."""
        return self.scene_weights if self.convention == "source" else self.weights

    def crop(self, x: Tensor) -> Tensor:
        """The sensor-sized central block of a padded-grid scene."""
        return crop(x, self.sensor_shape).contiguous()

    def pad(self, x: Tensor) -> Tensor:
        """A sensor-sized scene zero-filled into the padded grid."""
        return pad(x, self.grid_shape)

