r"""Forward operators of the lensless camera with exact adjoints (``A`` and ``A_adjoint``).

Thin :class:`torch.nn.Module` wrappers over :mod:`psfkit.forward`: they hold the kernels,
weight maps and cached spectra and check their inputs. ``A`` maps a scene ``(B, C, H', W')``
to a measurement of the same size. :class:`ShiftInvariantOperator`: ``y = crop(K * pad(x))``;
:class:`EigenKernelOperator`: Eq. 7 (sensor or source side). Spectra are cached for fixed
kernels and recomputed per call for trainable ones, so a network takes them once per forward
pass with :meth:`~FFTConvolutionOperator.prepare` and its :class:`PreparedOperator` applies
``A``/``Aᵀ`` with no kernel FFT.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ekdun.errors import ConfigurationError, KernelShapeError, TensorShapeError
from psfkit.forward.base import LinearOperator
from psfkit.forward.convolution import kernel_spectra
from psfkit.forward.geometry import CONVENTIONS, padded_shape
from psfkit.forward.kernel_checks import check_kernels
from psfkit.forward.kernelfile import KernelModel
from psfkit.forward.norm import spectral_bound
from psfkit.forward.operator import SpectralOperator, kernel_model_tensors
from psfkit.forward.weights import get_basis


class PreparedOperator(SpectralOperator):
    """A :class:`psfkit.forward.operator.SpectralOperator` (precomputed kernel spectra) whose
    ``A`` and ``A_adjoint`` check their input (:meth:`check`); built by
    :meth:`FFTConvolutionOperator.prepare`, which checked the kernels and weights."""

    def check(self, t: Tensor, what: str) -> None:
        """Raise :class:`~ekdun.errors.TensorShapeError` unless ``t`` fits this operator."""
        if t.ndim != 4:
            raise TensorShapeError(f"{what} must be (B, C, H, W), got shape {tuple(t.shape)}")
        h, w = int(t.shape[-2]), int(t.shape[-1])
        if (h, w) != self.sensor_shape:
            raise TensorShapeError(f"{what} is {h}x{w} but the operator's sensor is "
                                   f"{self.sensor_shape[0]}x{self.sensor_shape[1]}")
        if int(t.shape[1]) != self.channels:
            raise TensorShapeError(f"{what} has {int(t.shape[1])} channel(s) but the operator "
                                   f"has {self.channels}")
        if t.dtype != self.dtype:
            raise TensorShapeError(f"{what} is {t.dtype} but the operator is {self.dtype} "
                                   "(convert the operator with .to(dtype) or the input)")

    def A(self, x: Tensor) -> Tensor:
        """Forward model ``y = A x``, ``(B, C, H', W') → (B, C, H', W')``."""
        self.check(x, "scene")
        return self.forward(x)

    def A_adjoint(self, y: Tensor) -> Tensor:
        """Exact adjoint ``x = Aᵀ y``, ``(B, C, H', W') → (B, C, H', W')``."""
        self.check(y, "measurement")
        return self.adjoint(y)

    __call__ = A


def _as_tensor(array: np.ndarray | Tensor, dtype: torch.dtype | None) -> Tensor:
    if isinstance(array, Tensor):
        return array.detach().to(dtype=dtype if dtype is not None else array.dtype)
    return torch.as_tensor(np.asarray(array), dtype=dtype if dtype is not None
                           else torch.float32)


def psf_tensor(psf: np.ndarray | Tensor, dtype: torch.dtype | None) -> Tensor:
    """A measured PSF ``(C, H, W)`` or ``(H, W)`` (mono) as a ``(C, H, W)`` tensor."""
    t = _as_tensor(psf, dtype)
    t = t[None] if t.ndim == 2 else t
    if t.ndim != 3:
        raise KernelShapeError(f"a PSF must be (C, H, W), got shape {tuple(t.shape)}")
    return t


class FFTConvolutionOperator(nn.Module, LinearOperator):
    """Base of the FFT convolution operators (a :class:`~psfkit.forward.base.LinearOperator`):
    kernels, weights and spectra cache.

    Parameters
    ----------
    kernels : Tensor
        ``(K, C, Hk, Wk)`` real kernels, origins at ``(Hk//2, Wk//2)``, at most ``(H', W')``.
    weights : Tensor or None
        ``(K, H', W')`` weight maps, or ``None`` (then ``K`` must be 1).
    sensor_shape : (int, int)
        ``(H', W')``.
    convention : {"sensor", "source"}
    scene_padding : int
        ``P >= 2``: the convolution grid is ``(P·H', P·W')``.
    trainable : bool
        Kernels are an :class:`~torch.nn.Parameter` (else a buffer, with cached spectra).
    """

    def __init__(self, kernels: Tensor, weights: Tensor | None, sensor_shape: Sequence[int],
                 convention: str = "sensor", scene_padding: int = 2,
                 trainable: bool = False) -> None:
        super().__init__()
        sensor = _check_sensor_shape(sensor_shape)
        if not isinstance(scene_padding, int) or scene_padding < 2:
            raise ConfigurationError(f"scene_padding must be an integer >= 2, got "
                                     f"{scene_padding!r}")
        if convention not in CONVENTIONS:
            raise ConfigurationError(f"convention must be 'sensor' or 'source', got "
                                     f"{convention!r}")
        check_kernels(kernels, sensor, error=KernelShapeError)
        if weights is not None:
            if weights.ndim != 3 or tuple(weights.shape) != (kernels.shape[0], *sensor):
                raise KernelShapeError(
                    f"weight maps must be (K, H', W') = ({kernels.shape[0]}, {sensor[0]}, "
                    f"{sensor[1]}), got {tuple(weights.shape)}")
            weights = weights.to(kernels.dtype)
        elif kernels.shape[0] != 1:
            raise KernelShapeError(f"{kernels.shape[0]} kernels need weight maps")
        self.sensor_shape = sensor
        self.scene_padding = scene_padding
        self.grid_shape = padded_shape(sensor, scene_padding)
        self.convention = convention
        kernels = kernels.detach().clone()
        if trainable:
            self.kernels = nn.Parameter(kernels)
        else:
            self.register_buffer("kernels", kernels)
        self.register_buffer("weights", weights)
        # Derived from the kernels: never saved, recomputed in the module's dtype/device.
        self.register_buffer("_spectra_cache", None, persistent=False)
        self.register_buffer("_conj_spectra_cache", None, persistent=False)
        self.register_load_state_dict_post_hook(lambda module, _keys: module.refresh_spectra())
        self.refresh_spectra()

    @property
    def n_kernels(self) -> int:
        """Number of kernels ``K``."""
        return int(self.kernels.shape[0])

    @property
    def channels(self) -> int:
        """Number of channels ``C`` the operator acts on."""
        return int(self.kernels.shape[1])

    @property
    def dtype(self) -> torch.dtype:
        """The kernels' (and so the inputs') dtype."""
        return self.kernels.dtype

    @property
    def device(self) -> torch.device:  # type: ignore[override]
        """Where the kernels (and so the inputs) live."""
        return self.kernels.device

    def norm(self, **options: Any) -> float:
        """``‖A‖`` of the current kernels (on a fresh :meth:`prepare`: caches nothing)."""
        with torch.no_grad():
            return self.prepare().norm(**options)

    @property
    def trainable(self) -> bool:
        """Whether the kernels receive gradients (then spectra are never cached)."""
        return bool(self.kernels.requires_grad)

    def refresh_spectra(self) -> None:
        """Recompute the cached spectra of fixed kernels (after changing them in place)."""
        if self.kernels.requires_grad:
            self._spectra_cache = self._conj_spectra_cache = None
        else:
            with torch.no_grad():
                self._spectra_cache = kernel_spectra(self.kernels, self.grid_shape)
                self._conj_spectra_cache = self._spectra_cache.conj().resolve_conj()

    def _apply(self, fn: Any, recurse: bool = True) -> FFTConvolutionOperator:
        # Module.to(float64) would cast the complex cache to real (dropping the imaginary
        # part): drop it first and recompute it from the converted kernels.
        self._spectra_cache = self._conj_spectra_cache = None
        module = super()._apply(fn, recurse)
        self.refresh_spectra()
        return module

    def spectra(self, first: int | None = None) -> Tensor:
        """Kernel spectra ``(K, C, PH, PW//2 + 1)`` (the first ``first`` kernels); cached for
        fixed kernels, one FFT per kernel per call for trainable ones."""
        cache = self._spectra_cache
        if cache is not None and not self.kernels.requires_grad:
            return cache[:first]
        return kernel_spectra(self.kernels[:first], self.grid_shape)

    def _cached_conj(self, first: int | None = None) -> Tensor | None:
        cache = self._conj_spectra_cache
        if cache is None or self.kernels.requires_grad:
            return None
        return cache[:first]

    def prepare(self, spectra: Tensor | None = None,
                conj_spectra: Tensor | None = None) -> PreparedOperator:
        """This operator bound to ``spectra`` (default :meth:`spectra`) and optionally their
        materialised conjugates (else taken once, when the adjoint first needs them)."""
        if spectra is None:
            spectra, conj_spectra = self.spectra(), self._cached_conj()
        return PreparedOperator(spectra, self.weights, self.sensor_shape, self.grid_shape,
                                self.convention, conj_spectra)

    def lipschitz_bound(self) -> float:
        r"""``max_{k,c,ω} |K̂_k(ω)|²``, an upper bound of ``‖AᵀA‖`` for one kernel (not an
        estimate of ``‖A‖``): the unrolled networks' initial step-size scale."""
        with torch.no_grad():
            return spectral_bound(self.spectra()) ** 2

    def A(self, x: Tensor) -> Tensor:
        """Forward model ``y = A x`` (takes the kernel FFTs when the kernels are trainable)."""
        return self.prepare().A(x)

    def A_adjoint(self, y: Tensor) -> Tensor:
        """Exact adjoint ``Aᵀ y``."""
        return self.prepare().A_adjoint(y)

    def forward(self, x: Tensor) -> Tensor:
        """Same as :meth:`A` (what ``op(x)`` calls, so a subclass's ``A`` is followed)."""
        return self.A(x)

    def extra_repr(self) -> str:
        return (f"kernels={tuple(self.kernels.shape)}, sensor={self.sensor_shape}, "
                f"padding={self.scene_padding}, convention={self.convention!r}, "
                f"trainable={self.trainable}")


class ShiftInvariantOperator(FFTConvolutionOperator):
    r"""Shift-invariant lensless model ``y = crop(K * pad(x))``, ``Aᵀy = crop(K ⋆ pad(y))``.

    Parameters
    ----------
    psf : Tensor
        ``(C, Hk, Wk)`` kernel, origin at its centre.
    sensor_shape : (int, int), optional
        ``(H', W')``; default the PSF's size.
    scene_padding : int
    trainable : bool
    """

    def __init__(self, psf: Tensor, sensor_shape: Sequence[int] | None = None,
                 scene_padding: int = 2, trainable: bool = False) -> None:
        if psf.ndim != 3:
            raise KernelShapeError(f"a PSF must be (C, H, W), got shape {tuple(psf.shape)}")
        sensor = tuple(psf.shape[-2:]) if sensor_shape is None else sensor_shape
        super().__init__(psf[None], None, sensor, "sensor", scene_padding, trainable)

    @property
    def psf(self) -> Tensor:
        """``(C, Hk, Wk)`` kernel."""
        return self.kernels[0]

    @classmethod
    def from_psf(cls, psf: np.ndarray | Tensor, sensor_shape: Sequence[int] | None = None,
                 scene_padding: int = 2, trainable: bool = False,
                 dtype: torch.dtype | None = None) -> ShiftInvariantOperator:
        """From a measured PSF array ``(C, H, W)`` or ``(H, W)`` (mono), origin at its centre."""
        return cls(psf_tensor(psf, dtype), sensor_shape, scene_padding, trainable)


class EigenKernelOperator(FFTConvolutionOperator):
    r"""Eigen-kernel forward model (Eq. 7 and its generalisations) with exact adjoint.

    Sensor side (default)::

        A x  = Σ_k W_k ⊙ crop(K_k * pad(x))          1 FFT + K inverse FFTs
        Aᵀ y = crop(Σ_k K_k ⋆ pad(W_k ⊙ y))          K FFTs + 1 inverse FFT

    Source side::

        A x  = crop(Σ_k K_k * pad(W_k ⊙ x))          K FFTs + 1 inverse FFT
        Aᵀ y = Σ_k W_k ⊙ crop(K_k ⋆ pad(y))          1 FFT + K inverse FFTs

    Parameters
    ----------
    kernels : Tensor
        ``(K, C, Hk, Wk)``.
    weights : Tensor
        ``(K, H', W')`` weight maps.
    convention : {"sensor", "source"}
    scene_padding : int
    trainable : bool
    kernel_names : sequence of str, optional
    """

    def __init__(self, kernels: Tensor, weights: Tensor, convention: str = "sensor",
                 scene_padding: int = 2, trainable: bool = False,
                 kernel_names: Sequence[str] | None = None) -> None:
        if weights is None or weights.ndim != 3:
            raise KernelShapeError("an eigen-kernel operator needs (K, H', W') weight maps")
        super().__init__(kernels, weights, tuple(weights.shape[-2:]), convention,
                         scene_padding, trainable)
        names = tuple(kernel_names) if kernel_names is not None else tuple(
            f"k{i}" for i in range(self.n_kernels))
        if len(names) != self.n_kernels:
            raise KernelShapeError(f"{len(names)} kernel names for {self.n_kernels} kernels")
        self.kernel_names = names

    @classmethod
    def from_basis(cls, kernels: np.ndarray | Tensor, basis: str = "paper",
                   sensor_shape: Sequence[int] | None = None,
                   optical_center: tuple[float, float] | None = None,
                   convention: str = "sensor", scene_padding: int = 2, trainable: bool = False,
                   dtype: torch.dtype | None = None) -> EigenKernelOperator:
        """From kernels ``(K, C, Hk, Wk)`` and a :mod:`psfkit.forward.weights` basis name."""
        k = _as_tensor(kernels, dtype)
        sensor = _check_sensor_shape(tuple(k.shape[-2:]) if sensor_shape is None
                                     else sensor_shape)
        weight_basis = get_basis(basis)
        maps = torch.as_tensor(weight_basis.maps(sensor, optical_center), dtype=k.dtype)
        return cls(k, maps, convention, scene_padding, trainable, weight_basis.kernel_names)

    @classmethod
    def from_kernel_model(cls, model: KernelModel, trainable: bool = False,
                          dtype: torch.dtype = torch.float32) -> EigenKernelOperator:
        """From a kernel file's model, its arrays converted as for every command
        (:func:`psfkit.forward.operator.kernel_model_tensors`)."""
        kernels, maps = kernel_model_tensors(model, dtype)
        return cls(kernels, maps, model.convention, model.scene_padding, trainable,
                   model.kernel_names)

    def prepare_base(self, spectra: Tensor | None = None,
                     conj_spectra: Tensor | None = None) -> PreparedOperator:
        """The shift-invariant model of the base kernel alone; ``spectra`` (and
        ``conj_spectra``) may hold all kernels' (only the first is used)."""
        if spectra is None:
            spectra, conj_spectra = self.spectra(first=1), self._cached_conj(first=1)
        return PreparedOperator(spectra[:1], None, self.sensor_shape, self.grid_shape,
                                conj_spectra=None if conj_spectra is None else conj_spectra[:1])


def _check_sensor_shape(sensor_shape: Sequence[int]) -> tuple[int, int]:
    if len(sensor_shape) != 2 or min(int(s) for s in sensor_shape) < 2:
        raise KernelShapeError(f"sensor_shape {list(sensor_shape)} is not a valid size")
    return (int(sensor_shape[0]), int(sensor_shape[1]))
