"""The eigen-kernel operator of a kernel file, built in one place.

Every command that turns a kernel file into ``A`` (``fit-pairs``' predictions, classical
reconstruction, ekdun's networks via :func:`kernel_model_tensors`) goes through here, so the
same file gives the same numbers everywhere (Eq. 7, ``docs/architecture.md``).
:class:`SpectralOperator` applies ``A``/``Aᵀ`` to a sensor-sized scene with the kernel spectra
taken once; :class:`PaddedSceneOperator` is the same model with the scene on the whole padded
grid (the classical solvers).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.forward.base import LinearOperator
from psfkit.forward.convolution import (
    crop,
    eigen_kernel_adjoint,
    eigen_kernel_forward,
    kernel_spectra,
    pad,
    records_graph,
    zero_workspace,
)
from psfkit.forward.geometry import padded_shape
from psfkit.forward.padded_scene import padded_scene_adjoint, padded_scene_forward


class KernelFileModel(Protocol):
    """What the operators read of a kernel file's model (``KernelModel``)."""

    kernels: np.ndarray
    convention: str
    sensor_shape: tuple[int, int]
    scene_padding: int

    def weight_maps(self, extent: tuple[int, int] | None = None) -> np.ndarray: ...


def kernel_model_tensors(model: KernelFileModel, dtype: torch.dtype = torch.float32,
                         device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
    """A kernel file's kernels ``(K, C, Hk, Wk)`` and weights ``(K, H', W')`` as tensors."""
    kernels = torch.as_tensor(model.kernels, dtype=dtype, device=device)
    weights = torch.as_tensor(model.weight_maps(), dtype=dtype, device=device)
    return kernels, weights


_REAL_DTYPE = {torch.complex64: torch.float32, torch.complex128: torch.float64}


class SpectralOperator(LinearOperator):
    """An eigen-kernel operator (Eq. 7, either convention) bound to kernel spectra.

    Cheap to build (no copies): unrolled networks build one per forward pass.

    Parameters
    ----------
    spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` complex (:func:`~psfkit.forward.convolution.kernel_spectra`).
    weights : Tensor or None
        ``(K, H', W')`` real weight maps; ``None``: one kernel of weight 1.
    sensor_shape : (int, int)
        ``(H', W')``.
    grid_shape : (int, int)
        ``(PH, PW)``, the spectra's grid.
    convention : {"sensor", "source"}
    conj_spectra : Tensor, optional
        ``spectra.conj()`` materialised (taken once, lazily, when not given).
    """

    def __init__(self, spectra: Tensor, weights: Tensor | None, sensor_shape: tuple[int, int],
                 grid_shape: tuple[int, int], convention: str = "sensor",
                 conj_spectra: Tensor | None = None) -> None:
        self.spectra = spectra
        self._conj_spectra = conj_spectra
        self.weights = weights
        self.sensor_shape = (int(sensor_shape[0]), int(sensor_shape[1]))
        self.grid_shape = (int(grid_shape[0]), int(grid_shape[1]))
        self.convention = convention
        self.channels = int(spectra.shape[1])
        self.dtype = _REAL_DTYPE[spectra.dtype]
        self._workspace: Tensor | None = None

    @property
    def device(self) -> torch.device:
        """Where the spectra (and the inputs) live."""
        return self.spectra.device

    @property
    def n_kernels(self) -> int:
        """Number of kernels ``K`` (1 for the shift-invariant model)."""
        return int(self.spectra.shape[0])

    @property
    def conj_spectra(self) -> Tensor:
        """Conjugate spectra for the adjoint, materialised once (a lazy view copies each time)."""
        if self._conj_spectra is None:
            self._conj_spectra = self.spectra.conj().resolve_conj()
        return self._conj_spectra

    @classmethod
    def from_kernel_model(cls, model: KernelFileModel, dtype: torch.dtype = torch.float32,
                          device: torch.device | str | None = None) -> SpectralOperator:
        """The operator of a kernel file's model in working precision ``dtype``."""
        kernels, weights = kernel_model_tensors(model, dtype, device)
        sensor = (int(model.sensor_shape[0]), int(model.sensor_shape[1]))
        grid = padded_shape(sensor, model.scene_padding)
        with torch.no_grad():
            spectra = kernel_spectra(kernels, grid)
        return cls(spectra, weights, sensor, grid, model.convention,
                   spectra.conj().resolve_conj())

    def _workspace_for(self, t: Tensor) -> Tensor | None:
        """A zero-padded FFT input ``(..., PH, PW)`` reused across calls (reallocated on a new
        leading shape, dtype or device); ``None`` when autograd records ``t`` or the spectra."""
        if records_graph(t, self.spectra):
            return None
        ws = self._workspace
        if ws is None or ws.shape[:-2] != t.shape[:-2] or ws.dtype != t.dtype \
                or ws.device != t.device:
            ws = self._workspace = zero_workspace(t, self.grid_shape)
        return ws

    def forward(self, x: Tensor) -> Tensor:
        """``y = A x``, ``(B, C, H', W')`` → ``(B, C, H', W')``."""
        return eigen_kernel_forward(x, self.spectra, self.weights, self.grid_shape,
                                    self.convention, self._workspace_for(x))

    def adjoint(self, y: Tensor) -> Tensor:
        """``x = Aᵀ y``, ``(B, C, H', W')`` → ``(B, C, H', W')``."""
        return eigen_kernel_adjoint(y, self.conj_spectra, self.weights, self.grid_shape,
                                    self.convention, self._workspace_for(y))

    def A(self, x: Tensor) -> Tensor:
        """Same as :meth:`forward` (subclasses check their input first)."""
        return self.forward(x)

    def A_adjoint(self, y: Tensor) -> Tensor:
        """Same as :meth:`adjoint`."""
        return self.adjoint(y)


class PaddedSceneOperator(LinearOperator):
    """``A`` and ``Aᵀ`` of an eigen-kernel model with the scene on the whole padded grid
    (:func:`~psfkit.forward.padded_scene.padded_scene_forward`: a measurement also records
    light from outside the view, so the classical solvers solve on the padded grid). For a scene
    zero outside the view ``A pad(x)`` equals :class:`SpectralOperator`'s ``A x``.

    Parameters
    ----------
    base : SpectralOperator
        Its spectra, weights and grid.
    scene_weights : Tensor, optional
        ``(K, PH, PW)`` source-side weights whose central block is ``base.weights``
        (:meth:`from_kernel_model` builds them); unused otherwise.

    Raises
    ------
    ConfigurationError
        Source-side model without ``scene_weights``, or ones not matching the view's weights.
    """

    #: What :meth:`check` raises (ekdun's subclass raises its ``TensorShapeError``).
    shape_error: type[Exception] = InvalidInputError

    def __init__(self, base: SpectralOperator, scene_weights: Tensor | None = None) -> None:
        self.weights = base.weights
        if self.weights is not None and bool((self.weights == 1).all()):
            self.weights = None                 # shift-invariant: either convention
        self.convention = "sensor" if self.weights is None else base.convention
        self.base = base
        self.sensor_shape = base.sensor_shape
        self.grid_shape = base.grid_shape
        self.device = base.device
        self.channels = base.channels
        self.dtype = base.dtype
        self.scene_weights: Tensor | None = None
        if self.convention == "source":
            self.scene_weights = self._checked_scene_weights(scene_weights)

    def _checked_scene_weights(self, scene_weights: Tensor | None) -> Tensor:
        if scene_weights is None:
            raise ConfigurationError(
                "the extended scene of a source-side model needs its weights on the padded "
                "grid (from_kernel_model builds them)")
        assert self.weights is not None
        shape = (int(self.base.spectra.shape[0]), *self.grid_shape)
        if tuple(scene_weights.shape) != shape or not torch.allclose(
                crop(scene_weights, self.sensor_shape), self.weights.to(scene_weights.dtype),
                rtol=1e-5, atol=1e-6):
            raise ConfigurationError(
                f"scene weights must be {shape} and equal the model's weights in the view")
        return scene_weights.to(self.dtype).contiguous()

    @classmethod
    def from_kernel_model(cls, model: KernelFileModel, dtype: torch.dtype = torch.float32
                          ) -> PaddedSceneOperator:
        """The padded-scene operator of a kernel file's model (either convention)."""
        base = SpectralOperator.from_kernel_model(model, dtype)
        scene_weights = None
        if model.convention == "source" and model.kernels.shape[0] > 1:
            scene_weights = torch.as_tensor(model.weight_maps(extent=base.grid_shape),
                                            dtype=dtype)
        return cls(base, scene_weights)

    def check(self, y: Tensor, what: str) -> None:
        """Raise :attr:`shape_error` unless ``y`` is a ``(B, C, H', W')`` measurement here."""
        if y.ndim != 4 or tuple(y.shape[-2:]) != self.sensor_shape \
                or int(y.shape[1]) != self.channels or y.dtype != self.dtype:
            raise self.shape_error(f"{what} must be (B, {self.channels}, "
                                   f"{self.sensor_shape[0]}, {self.sensor_shape[1]}) "
                                   f"{self.dtype}, got {tuple(y.shape)} {y.dtype}")

    def domain_shape(self) -> tuple[int, ...]:
        """``(1, C, PH, PW)``: a scene on the padded grid."""
        return (1, self.channels, *self.grid_shape)

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
